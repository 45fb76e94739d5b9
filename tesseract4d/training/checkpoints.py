"""Training checkpoints: one folder per saved step, written whole, rotated, resumed from the newest intact one.

    RUN/checkpoint-XXXXXX/        CHECKPOINT_PREFIX + the step: what the trainer writes into it, plus
    RUN/checkpoint-XXXXXX/trainer_state.json   STATE_FILE (step, schedule, elapsed time, the trainer's own)

A checkpoint is written into a hidden sibling folder and renamed into place (signals held for the
swap), so a stop or a crash mid-write leaves the previous checkpoints as they were; the newest
``keep`` are kept. Optimiser and RNG state are stored without pickle (safetensors + JSON).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tesseract4d.errors import UserError
from tesseract4d.outputs import files_as_created, signals_held

CHECKPOINT_PREFIX = "checkpoint-"
STATE_FILE = "trainer_state.json"


def list_checkpoints(run: str | os.PathLike) -> list[Path]:
    """The run's checkpoint folders with a state file, oldest first."""
    return sorted(p for p in Path(run).glob(f"{CHECKPOINT_PREFIX}*") if p.is_dir() and (p / STATE_FILE).is_file())


def checkpoint_dir(run: str | os.PathLike, step: int) -> Path:
    return Path(run) / f"{CHECKPOINT_PREFIX}{int(step):06d}"


def write_checkpoint(run: str | os.PathLike, step: int, state: dict, write: Callable[[Path], None],
                     keep: int = 2) -> Path:
    """Write the checkpoint of ``step``: ``write(folder)`` fills a fresh hidden folder, ``state`` (with
    ``step``) becomes its STATE_FILE, and the folder is renamed into place; then all but the newest
    ``keep`` (at least 1) checkpoints are removed. Returns the checkpoint folder."""
    final = checkpoint_dir(run, step)
    tmp = final.with_name(f".{final.name}.tmp")  # this run's own name; one a killed run left is replaced
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    write(tmp)
    (tmp / STATE_FILE).write_text(json.dumps({**state, "step": int(step)}, indent=2))
    files_as_created(tmp)  # safetensors writes 0600
    with signals_held():
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
    for old in list_checkpoints(run)[:-max(1, int(keep))]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def read_state(checkpoint: str | os.PathLike) -> dict:
    return json.loads((Path(checkpoint) / STATE_FILE).read_text())


def resume_newest(run: str | os.PathLike, load: Callable[[Path, dict], None]) -> Path:
    """Load the newest intact checkpoint of ``run`` with ``load(folder, state)``, saying which ones were
    skipped as damaged (unreadable state or weights). A UserError when there is none, or none intact."""
    from safetensors import SafetensorError

    checkpoints = list_checkpoints(run)
    if not checkpoints:
        raise UserError(f"--resume: {run} holds no checkpoint ({CHECKPOINT_PREFIX}XXXXXX/) to resume from; "
                        f"drop --resume to start a new run")
    for ckpt in reversed(checkpoints):
        try:
            state = read_state(ckpt)
            load(ckpt, state)
        except (SafetensorError, OSError, ValueError, KeyError) as e:
            print(f"warning: checkpoint {ckpt} is damaged ({type(e).__name__}: {str(e).splitlines()[0][:120]}); "
                  f"trying an older one", flush=True)
            continue
        if ckpt != checkpoints[-1]:
            print(f"resuming from {ckpt.name} (step {state.get('step')}), the newest intact checkpoint", flush=True)
        return ckpt
    raise UserError(f"every checkpoint in {run} is damaged; start a new run with another --out")


# --------------------------------------------------------------------------- state without pickle


def save_optimizer(optimizer: torch.optim.Optimizer, folder: Path) -> None:
    from safetensors.torch import save_file

    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for idx, st in sd["state"].items():
        for key, value in st.items():
            if torch.is_tensor(value):
                tensors[f"{idx}.{key}"] = value.detach().cpu().contiguous()
            else:
                scalars[f"{idx}.{key}"] = value
    save_file(tensors, str(folder / "optimizer.safetensors"))
    (folder / "optimizer.json").write_text(json.dumps({"param_groups": sd["param_groups"], "scalars": scalars}))


def load_optimizer(optimizer: torch.optim.Optimizer, folder: Path) -> None:
    from safetensors.torch import load_file

    tensors = load_file(str(folder / "optimizer.safetensors"))
    meta = json.loads((folder / "optimizer.json").read_text())
    state: dict[int, dict] = {}
    for name, value in list(tensors.items()) + list(meta["scalars"].items()):
        idx, key = name.split(".", 1)
        state.setdefault(int(idx), {})[key] = value
    optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def save_rng(folder: Path) -> None:
    """Global RNG states (the trainers themselves draw from per-step generators)."""
    from safetensors.torch import save_file

    tensors = {"torch_cpu": torch.get_rng_state()}
    if torch.cuda.is_available():
        for i, s in enumerate(torch.cuda.get_rng_state_all()):
            tensors[f"cuda_{i}"] = s
    save_file(tensors, str(folder / "rng_state.safetensors"))
    np_state = np.random.get_state()
    (folder / "rng_state.json").write_text(json.dumps({"numpy": [np_state[0], np_state[1].tolist(), *np_state[2:]]}))


def load_rng(folder: Path) -> None:
    from safetensors.torch import load_file

    tensors = load_file(str(folder / "rng_state.safetensors"))
    torch.set_rng_state(tensors["torch_cpu"])
    if torch.cuda.is_available():
        states = [tensors[k] for k in sorted(tensors) if k.startswith("cuda_")]
        if states:
            torch.cuda.set_rng_state_all(states)
    s = json.loads((folder / "rng_state.json").read_text())["numpy"]
    np.random.set_state((s[0], np.asarray(s[1], dtype=np.uint32), *s[2:]))
