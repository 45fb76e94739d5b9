"""How an inference checkpoint of a latent preset carries its RGB-D-N autoencoder.

The exported folder holds a copy of the autoencoder (``CKPT/autoencoder/``) and its hash in
``tesseract4d_config.json``; loading refuses a checkpoint whose autoencoder is missing or differs.
A decoder fine-tuned on the same latents can replace the checkpoint's (``replace_decoder``).

Two checkpoints side by side that carry the same autoencoder may store it once, as the shipped
``v2-2step`` reads ``v2``'s: the second's config then names its sibling's folder (``dir``:
``../SIBLING/autoencoder``), and a copy written elsewhere (``checkpoint set-sampler --to``, ``checkpoint swap-decoder``)
takes its own copy of it again (``own_autoencoder``).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import DECODER_FIELDS, ENCODER_PREFIXES

AUTOENCODER_DIR = "autoencoder"


def autoencoder_entry(codec, autoencoder_dir: str | None) -> dict:
    """The inference config's record of the codec's autoencoder."""
    return {"hash": codec.autoencoder_hash, "source_dir": autoencoder_dir, "dir": AUTOENCODER_DIR,
            "config": codec.autoencoder.config.to_dict()}


def copy_autoencoder(entry: dict, checkpoint_dir: Path) -> Path:
    """Copy the autoencoder recorded in ``entry`` into ``checkpoint_dir``/autoencoder, checking its hash."""
    from tesseract4d.model.autoencoder import autoencoder_hash

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
    from tesseract4d.model.autoencoder import autoencoder_hash

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
    return {**config, "autoencoder": _own_entry(entry)}


def _own_entry(entry: dict) -> dict:
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


def replace_decoder(checkpoint: str | os.PathLike, autoencoder: str | os.PathLike, to: str | os.PathLike,
                    half: bool = False, overwrite: bool = False) -> Path:
    """Write a copy of the latent ``checkpoint`` into ``to`` whose autoencoder is ``autoencoder``: a
    decoder-only fine-tune of the checkpoint's own (``train-autoencoder --decoder-only``), so the
    transformer's latents are unchanged. Refused, naming what differs, when its encoder, latent
    statistics or architecture are not the checkpoint's. ``half`` stores the new decoder in float16
    (the encoder is copied as the checkpoint stores it, the transformer as it is)."""
    from tesseract4d.model.autoencoder import WEIGHTS_FILE as AE_WEIGHTS
    from tesseract4d.model.autoencoder import autoencoder_hash, load_autoencoder, read_autoencoder_config
    import torch
    from safetensors.torch import load_file, save_file

    from tesseract4d.model.checkpoint import INFERENCE_CONFIG_FILE, SCHEDULER_DIR, TRANSFORMER_DIR, read_inference_config
    from tesseract4d.outputs import OutputDir

    checkpoint, autoencoder = Path(checkpoint), Path(autoencoder)
    config = read_inference_config(checkpoint)
    if "autoencoder" not in config:
        raise UserError(f"{checkpoint} is a pixel-space checkpoint (preset {config.get('preset', {}).get('name')!r}); "
                        f"only a latent checkpoint has a decoder to replace")
    old_dir = checkpoint_autoencoder(checkpoint, config["autoencoder"])
    read_autoencoder_config(autoencoder)  # a UserError naming the fix when it is not an autoencoder
    diff = encoder_differences(load_autoencoder(old_dir), load_autoencoder(autoencoder))
    if diff:
        raise UserError(f"{autoencoder} does not encode like {old_dir} ({'; '.join(diff[:3])}"
                        f"{'; ...' if len(diff) > 3 else ''}); make it with `tesseract4d train-autoencoder "
                        f"--recipe ae-f8c32-decoder --init {old_dir}`")
    with OutputDir(to, "swap-decoder", inputs=[checkpoint, autoencoder], overwrite=overwrite, flag="--to") as tmp:
        shutil.copytree(checkpoint / TRANSFORMER_DIR, tmp / TRANSFORMER_DIR)
        shutil.copytree(checkpoint / SCHEDULER_DIR, tmp / SCHEDULER_DIR)
        dst = tmp / AUTOENCODER_DIR
        dst.mkdir()
        for name in ("config.json", "fidelity.json"):
            if (autoencoder / name).is_file():
                shutil.copy2(autoencoder / name, dst / name)
        # The encoder's tensors are the checkpoint's own, as stored (float16 stays float16), so its
        # latents stay bit-identical; the rest comes from the new autoencoder (float16 with ``half``).
        old_weights, new_weights = load_file(str(old_dir / AE_WEIGHTS)), load_file(str(autoencoder / AE_WEIGHTS))
        merged = {k: old_weights[k] if k.startswith(ENCODER_PREFIXES) else
                  (v.half() if half and v.dtype == torch.float32 else v) for k, v in new_weights.items()}
        save_file({k: v.contiguous() for k, v in merged.items()}, str(dst / AE_WEIGHTS))
        old = config["autoencoder"]
        config["autoencoder"] = {
            **_own_entry(old), "hash": autoencoder_hash(dst), "source_dir": str(autoencoder),
            # The autoencoder the transformer was trained with: its encoder is this one's.
            "trained_with_hash": old.get("trained_with_hash", old["hash"]),
            "decoder_replaced": {"previous_hash": old["hash"], "source_hash": autoencoder_hash(autoencoder)},
        }
        (tmp / INFERENCE_CONFIG_FILE).write_text(json.dumps(config, indent=2))
    return Path(to)
