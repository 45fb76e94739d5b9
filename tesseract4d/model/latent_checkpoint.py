"""How an inference checkpoint of a latent preset carries its RGB-D-N autoencoder.

The exported folder holds a copy of the autoencoder (``CKPT/autoencoder/``) and its hash in
``tesseract4d_config.json``; loading refuses a checkpoint whose autoencoder is missing or differs.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tesseract4d.errors import UserError

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
        raise UserError(f"{checkpoint_dir} is a latent checkpoint without its autoencoder ({folder} is missing); "
                        f"re-export it with `tesseract4d train --export RUN --to {checkpoint_dir}`")
    found = autoencoder_hash(folder)
    if found != entry["hash"]:
        raise UserError(f"{folder} is autoencoder {found}, but {checkpoint_dir} was trained on {entry['hash']}; "
                        f"re-export the checkpoint with `tesseract4d train --export RUN` (it copies the right one)")
    return folder
