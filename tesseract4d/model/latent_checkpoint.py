"""How an inference checkpoint of a latent preset carries its RGB-D-N autoencoder.

The exported folder holds a copy of the autoencoder (``CKPT/autoencoder/``) and its hash in
``tesseract4d_config.json``; loading refuses a checkpoint whose autoencoder is missing or differs.
A decoder fine-tuned on the same latents can replace the checkpoint's (``checkpoint_copies.replace_decoder``).

Two checkpoints side by side that carry the same autoencoder may store it once, as the shipped
``v2-2step`` reads ``v2``'s: the second's config then names its sibling's folder (``dir``:
``../SIBLING/autoencoder``), and a copy written elsewhere (``checkpoint set-sampler --to``, ``checkpoint swap-decoder``)
takes its own copy of it again (``own_autoencoder``).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import DECODER_FIELDS, ENCODER_PREFIXES, autoencoder_hash

AUTOENCODER_DIR = "autoencoder"


def autoencoder_entry(codec, autoencoder_dir: str | None) -> dict:
    """The inference config's record of the codec's autoencoder."""
    return {"hash": codec.autoencoder_hash, "source_dir": autoencoder_dir, "dir": AUTOENCODER_DIR,
            "config": codec.autoencoder.config.to_dict()}


def copy_autoencoder(entry: dict, checkpoint_dir: Path) -> Path:
    """Copy the autoencoder recorded in ``entry`` into ``checkpoint_dir``/autoencoder, checking its hash."""
    src = Path(entry["source_dir"] or "")
    if not (src / "config.json").is_file() or autoencoder_hash(src) != entry["hash"]:
        raise UserError(f"the autoencoder this run trained with ({src}, hash {entry['hash']}) is missing or was "
                        f"changed since; restore it, or retrain with `tesseract4d train --autoencoder DIR`")
    dst = Path(checkpoint_dir) / AUTOENCODER_DIR
    dst.mkdir(parents=True)
    for name in ("config.json", "model.safetensors", "fidelity.json"):
        if (src / name).is_file():
            shutil.copy2(src / name, dst / name)
    return dst


def checkpoint_autoencoder(checkpoint_dir: Path, entry: dict) -> Path:
    """The checkpoint's autoencoder folder, after checking it is there and is the one it was trained with."""
    folder = Path(checkpoint_dir) / entry.get("dir", AUTOENCODER_DIR)
    if not (folder / "config.json").is_file() or not (folder / "model.safetensors").is_file():
        if shares_autoencoder(entry):
            raise UserError(f"{checkpoint_dir} shares the autoencoder of the checkpoint beside it ({folder}), which "
                            f"is missing; keep the two folders side by side (copy both), as they were shipped")
        raise UserError(f"{checkpoint_dir} is a latent checkpoint without its autoencoder ({folder} is missing); "
                        f"re-export it with `tesseract4d checkpoint export RUN --to {checkpoint_dir}`")
    found = autoencoder_hash(folder)
    if found != entry["hash"]:
        raise UserError(f"{folder} is autoencoder {found}, but {checkpoint_dir} was trained on {entry['hash']}; "
                        f"re-export the checkpoint with `tesseract4d checkpoint export RUN` (it copies the right one)")
    return folder


def shares_autoencoder(entry: dict) -> bool:
    """Whether a checkpoint reads the autoencoder of the checkpoint beside it instead of its own copy."""
    return entry.get("dir", AUTOENCODER_DIR) != AUTOENCODER_DIR


def own_autoencoder(checkpoint: Path, config: dict, folder: Path) -> dict:
    """For a copy of ``checkpoint`` being written into ``folder`` (anywhere): where the checkpoint
    shares its sibling's autoencoder, copy that autoencoder into ``folder``/autoencoder and return the
    config naming the copy's own; otherwise the config as it is."""
    entry = config.get("autoencoder")
    if entry is None or not shares_autoencoder(entry):
        return config
    source = checkpoint_autoencoder(checkpoint, entry)
    shutil.copytree(source, Path(folder) / AUTOENCODER_DIR)
    return {**config, "autoencoder": own_entry(entry)}


def own_entry(entry: dict) -> dict:
    """An autoencoder entry naming the checkpoint's own copy (AUTOENCODER_DIR), not a sibling's."""
    return {**{k: v for k, v in entry.items() if k != "shared_with"}, "dir": AUTOENCODER_DIR}


def encoder_differences(a, b) -> list[str]:
    """What differs between the latent side (architecture, encoder weights, latent statistics) of two
    RGBDNAutoencoders; empty when ``b``'s latents are ``a``'s, bit for bit."""
    import torch

    out = []
    ca, cb = a.config.to_dict(), b.config.to_dict()
    out += [f"config {k}: {ca[k]} vs {cb[k]}" for k in ca if k not in DECODER_FIELDS and ca[k] != cb.get(k)]
    if out:
        return out
    sa, sb = a.state_dict(), b.state_dict()
    for key in sa:
        if key.startswith(ENCODER_PREFIXES) and not torch.equal(sa[key].float(), sb[key].float()):
            out.append(f"weight {key}")
    return out
