"""The inference checkpoint format: the one module that knows a checkpoint folder's layout.

    CKPT/tesseract4d_config.json        INFERENCE_CONFIG_FILE: format, version, preset, resolution,
                                        frames, depth range, text encoder, camera, training summary
    CKPT/transformer/config.json        TRANSFORMER_DIR: the RGBDNTransformer, diffusers format
    CKPT/transformer/diffusion_pytorch_model.safetensors     WEIGHTS_FILE (EMA weights)
    CKPT/scheduler/scheduler_config.json                     SCHEDULER_DIR: the sampler's settings

Versions: 1 had no scheduler folder (it sampled with ``pipeline.make_scheduler()``'s settings, which are
what it was trained for); 2 saves the scheduler with the weights. A checkpoint of another format or
of a newer version fails with a message that says what to do.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from tesseract4d.errors import UserError

FORMAT = "tesseract4d-checkpoint"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
INFERENCE_CONFIG_FILE = "tesseract4d_config.json"
TRANSFORMER_DIR = "transformer"
SCHEDULER_DIR = "scheduler"
# Where checkpoints written before autoguidance was removed kept its guide network: never loaded, and
# left out of the copies `set-sampler` writes.
REMOVED_GUIDE_DIR = "guide_transformer"
WEIGHTS_FILE = "diffusion_pytorch_model.safetensors"  # diffusers' name for safetensors weights
MODEL_CONFIG_FILE = "config.json"  # diffusers' name for a model's config
SCHEDULER_CONFIG_FILE = "scheduler_config.json"  # diffusers' name for a scheduler's config
MODEL_CARD_FILE = "MODEL_CARD.md"  # a shipped checkpoint's description of itself
CHECKPOINTS_DIR = Path(__file__).resolve().parent.parent / "checkpoints"  # what the package ships
# The default of `predict`, `demo`, `evaluate --heldout`, `rollout` and the viewer's Generate panel:
# v2 distilled into a 2-step sampler without guidance (one network pass per step).
SHIPPED_CHECKPOINT = CHECKPOINTS_DIR / "v2-2step"
# v2 itself (10 steps, text guidance 1.5): the teacher of the default, kept for comparison and distillation.
V2_CHECKPOINT = CHECKPOINTS_DIR / "v2"


def format_header() -> dict:
    """The fields that open every INFERENCE_CONFIG_FILE."""
    return {"format": FORMAT, "version": FORMAT_VERSION}


def write_inference_files(folder: str | os.PathLike, inference_config: dict) -> None:
    """Write INFERENCE_CONFIG_FILE (opening with :func:`format_header`) and the scheduler into
    ``folder``; the transformer is written by its own ``save_pretrained``."""
    # deferred: imports torch (heavy)
    from tesseract4d.model.pipeline import make_scheduler

    folder = Path(folder)
    (folder / INFERENCE_CONFIG_FILE).write_text(json.dumps(inference_config, indent=2))
    make_scheduler().save_pretrained(folder / SCHEDULER_DIR)


def weights_to_half(weights: Path) -> None:
    """Rewrite a safetensors file with its float32 tensors as float16 (other dtypes kept)."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(weights), "pt") as f:
        metadata = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    tensors = {k: v.half() if v.dtype == torch.float32 else v for k, v in tensors.items()}
    save_file(tensors, str(weights), metadata=metadata)


def weights_digest(checkpoint: str | os.PathLike) -> str:
    """SHA-256 (first 16 hex digits) of a checkpoint's transformer weights: what a run started from
    (``train --init``) or distilled (reflow pairs) names it by."""
    import hashlib

    h = hashlib.sha256()
    with open(Path(checkpoint) / TRANSFORMER_DIR / WEIGHTS_FILE, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def read_inference_config(checkpoint: str | os.PathLike) -> dict:
    """INFERENCE_CONFIG_FILE of a checkpoint folder, checked for format and version; UserError
    with the fix when the folder is not a (readable) inference checkpoint."""
    ckpt = Path(checkpoint)
    if not ckpt.is_dir():
        raise UserError(f"checkpoint {ckpt} {'is a file, not a folder' if ckpt.exists() else 'not found'}; pass a folder written by `tesseract4d train` (RUN/final) "
                        f"or `tesseract4d checkpoint export RUN --to DIR`")
    cfg_path = ckpt / INFERENCE_CONFIG_FILE
    if not cfg_path.is_file() or not (ckpt / TRANSFORMER_DIR / WEIGHTS_FILE).is_file():
        if (ckpt / "trainer_state.json").is_file():
            hint = " (a training checkpoint: export it with `tesseract4d checkpoint export RUN`)"
        elif (ckpt / "final" / INFERENCE_CONFIG_FILE).is_file():
            hint = f"; it is a training run folder: pass its export, --checkpoint {ckpt / 'final'}"
        else:
            hint = ""
        raise UserError(f"{ckpt} is not a tesseract4d inference checkpoint: it needs {INFERENCE_CONFIG_FILE} and "
                        f"{TRANSFORMER_DIR}/{WEIGHTS_FILE}{hint}")
    try:
        cfg = json.loads(cfg_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"{cfg_path} is corrupt ({type(e).__name__}: {e}); re-export the checkpoint") from e
    if not isinstance(cfg, dict) or cfg.get("format") != FORMAT:
        raise UserError(f"{cfg_path} is not a {FORMAT} config; pass a folder written by `tesseract4d train`")
    version = cfg.get("version")
    if version not in READABLE_VERSIONS:
        raise UserError(f"{ckpt} is checkpoint format version {version!r}; this tesseract4d reads versions "
                        f"{', '.join(map(str, READABLE_VERSIONS))}: update tesseract4d, or re-export the checkpoint with this one")
    return cfg


def load_scheduler(checkpoint: str | os.PathLike, config: dict):
    """The checkpoint's sampler: SCHEDULER_DIR when saved (version 2), else the version-1 sampler."""
    from diffusers import FlowMatchEulerDiscreteScheduler

    # deferred: imports torch (heavy)
    from tesseract4d.model.pipeline import make_scheduler

    folder = Path(checkpoint) / SCHEDULER_DIR
    if config["version"] == 1:
        return make_scheduler()
    if not (folder / SCHEDULER_CONFIG_FILE).is_file():
        raise UserError(f"{folder / SCHEDULER_CONFIG_FILE} is missing; re-export the checkpoint with `tesseract4d checkpoint export RUN`")
    return FlowMatchEulerDiscreteScheduler.from_pretrained(folder)


def load_transformer(checkpoint: str | os.PathLike, preset, modality_channels: dict[str, int]):
    """The checkpoint's RGBDNTransformer (``from_pretrained``), checked against the preset and the
    codec's ``modality_channels`` first, so a mismatch says which setting differs."""
    # deferred: imports diffusers, torch (heavy)
    from tesseract4d.model.rgbdn_transformer import RGBDNTransformer

    folder = Path(checkpoint) / TRANSFORMER_DIR
    try:
        saved = json.loads((folder / MODEL_CONFIG_FILE).read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"{folder / MODEL_CONFIG_FILE} is unreadable ({type(e).__name__}: {e}); re-export the checkpoint") from e
    missing = [k for k in ("backbone_config", "modality_channels") if not isinstance(saved.get(k), dict)]
    if missing:
        raise UserError(f"{folder / MODEL_CONFIG_FILE} lacks {', '.join(missing)}; it is not a tesseract4d transformer "
                        f"config: re-export the checkpoint")
    expected_channels = dict(modality_channels)
    if saved.get("modality_channels") != expected_channels:
        raise UserError(f"{folder} has modality channels {saved.get('modality_channels')} but preset "
                        f"{preset.name!r} needs {expected_channels}; the weights belong to another preset")
    if preset.backbone:
        mismatch = {k: (saved.get("backbone_config", {}).get(k), v) for k, v in preset.backbone.items()
                    if saved.get("backbone_config", {}).get(k) != v}
        if mismatch:
            raise UserError(f"{folder} does not match preset {preset.name!r}: "
                            + ", ".join(f"{k} is {a}, preset has {b}" for k, (a, b) in mismatch.items()))
    from safetensors import SafetensorError, safe_open

    try:  # the header lists every tensor's byte range: a truncated or garbled file fails here
        with safe_open(str(folder / WEIGHTS_FILE), "pt") as weights:
            weights.keys()
    except (SafetensorError, OSError) as e:
        raise UserError(f"{folder / WEIGHTS_FILE} is corrupt or truncated ({e}); re-export the checkpoint") from e
    try:
        model = RGBDNTransformer.from_pretrained(folder).float()  # weights may be stored in float16
    except (RuntimeError, ValueError, OSError, TypeError) as e:
        raise UserError(f"{folder}: weights do not match the config of preset {preset.name!r} "
                        f"({str(e).splitlines()[0]} ...); re-export the checkpoint") from e
    return model.eval()


# The preset fields that only say how a checkpoint samples (the weights do not depend on them).
SAMPLER_FIELDS = ("num_steps", "text_guidance", "image_guidance", "guidance_min_sigma", "static_tolerance", "draws")
# The preset fields of a noise-level interval (0: every step).
_INTERVAL_FIELDS = ("guidance_min_sigma",)


def check_sampler_settings(settings: dict) -> None:
    """UserError naming the flag when a sampler setting is out of range."""
    import math

    flags = {"num_steps": "--steps", "text_guidance": "--text-guidance", "image_guidance": "--set image_guidance",
             "guidance_min_sigma": "--set guidance_min_sigma", "static_tolerance": "--set static_tolerance",
             "draws": "--set draws"}
    for name, value in settings.items():
        if name not in SAMPLER_FIELDS:
            raise UserError(f"{name!r} is not a sampler setting (one of {', '.join(SAMPLER_FIELDS)})")
        if name in ("num_steps", "draws"):
            if int(value) != value or value < 1:
                what = "steps" if name == "num_steps" else "noise draws (1: a single draw)"
                raise UserError(f"{flags[name]} must be a whole number of {what} ≥ 1, got {value}")
        elif name == "static_tolerance":
            if not math.isfinite(value) or value < 0:
                raise UserError(f"{flags[name]} must be a finite number ≥ 0 (0: off), got {value}")
        elif not math.isfinite(value) or value < 0 or (name not in _INTERVAL_FIELDS and value == 0):
            what = "≥ 0 (0: guidance at every step)" if name in _INTERVAL_FIELDS else "> 0 (1: no guidance)"
            raise UserError(f"{flags[name]} must be a finite number {what}, got {value}")


def copy_checkpoint_files(checkpoint: Path, folder: Path, skip: tuple[str, ...] = ()) -> None:
    """Copy a checkpoint folder's files and folders into ``folder`` (a new checkpoint being written),
    all but its INFERENCE_CONFIG_FILE (the writer's to write), hidden files (an output marker) and
    the names in ``skip``."""
    import shutil

    for child in sorted(Path(checkpoint).iterdir()):
        if child.name == INFERENCE_CONFIG_FILE or child.name.startswith(".") or child.name in skip:
            continue
        (shutil.copytree if child.is_dir() else shutil.copy2)(child, Path(folder) / child.name)
