"""The inference checkpoint format: the one module that knows a checkpoint folder's layout.

    CKPT/tesseract4d_config.json        INFERENCE_CONFIG_FILE: format, version, preset, resolution,
                                        frames, depth range, text encoder, camera, training summary
    CKPT/transformer/config.json        TRANSFORMER_DIR: the RGBDNTransformer, diffusers format
    CKPT/transformer/diffusion_pytorch_model.safetensors     WEIGHTS_FILE (EMA weights)
    CKPT/scheduler/scheduler_config.json                     SCHEDULER_DIR: the sampler's settings
    CKPT/guide_transformer/...          GUIDE_DIR (optional): a weaker network of the same latent space
                                        that autoguidance steers away from (``set-sampler --guide``);
                                        its weights may be stored in 8 bits (``--guide-bits 8``,
                                        QUANTIZED_METADATA), loaded back as float32

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
GUIDE_DIR = "guide_transformer"
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


# Safetensors metadata of weights stored in 8 bits: every float matrix as int8 with one float16 scale
# per output row (the tensor NAME + QUANTIZED_SCALE_SUFFIX); vectors (biases, norms) kept as they are.
QUANTIZED_METADATA = {"tesseract4d_weights": "int8-per-output-channel"}
QUANTIZED_SCALE_SUFFIX = ".int8_scale"


def weights_to_int8(weights: Path) -> None:
    """Rewrite a safetensors file with each float tensor of ≥ 2 dimensions as int8 (symmetric, one
    scale per output row, ``round(w / scale)`` in [-127, 127]): half the bytes of float16."""
    import torch
    from safetensors.torch import load_file, save_file

    out = {}
    for name, w in load_file(str(weights)).items():
        if w.is_floating_point() and w.ndim >= 2:
            rows = w.float().reshape(w.shape[0], -1)
            scale = (rows.abs().amax(dim=1) / 127.0).clamp_min(1e-12).half()
            out[name] = (rows / scale.float()[:, None]).round().clamp(-127, 127).to(torch.int8).reshape(w.shape)
            out[name + QUANTIZED_SCALE_SUFFIX] = scale
        else:
            out[name] = w
    save_file(out, str(weights), metadata=QUANTIZED_METADATA)


def _in_8_bits(metadata: dict | None) -> bool:
    """Whether a safetensors file's metadata says ``weights_to_int8`` wrote it."""
    return (metadata or {}).items() >= QUANTIZED_METADATA.items()


def read_weights(weights: Path) -> tuple[dict, bool]:
    """A safetensors file's tensors, floats as float32 (8-bit ones dequantized), and whether it was
    stored in 8 bits."""
    from safetensors import safe_open

    with safe_open(str(weights), "pt") as f:
        quantized = _in_8_bits(f.metadata())
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    out = {}
    for name, v in tensors.items():
        if name.endswith(QUANTIZED_SCALE_SUFFIX):
            continue
        scale = tensors.get(name + QUANTIZED_SCALE_SUFFIX) if quantized else None
        if scale is not None:
            v = (v.float().reshape(v.shape[0], -1) * scale.float()[:, None]).reshape(v.shape)
        out[name] = v.float() if v.is_floating_point() else v
    return out, quantized


def weights_digest(checkpoint: str | os.PathLike, subfolder: str = TRANSFORMER_DIR) -> str:
    """SHA-256 (first 16 hex digits) of a checkpoint's transformer weights: what a run started from
    (``train --init``) or distilled (reflow pairs) names it by. ``subfolder`` GUIDE_DIR: its guide's."""
    import hashlib

    h = hashlib.sha256()
    with open(Path(checkpoint) / subfolder / WEIGHTS_FILE, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def read_inference_config(checkpoint: str | os.PathLike) -> dict:
    """INFERENCE_CONFIG_FILE of a checkpoint folder, checked for format and version; UserError
    with the fix when the folder is not a (readable) inference checkpoint."""
    ckpt = Path(checkpoint)
    if not ckpt.is_dir():
        raise UserError(f"checkpoint {ckpt} {'is a file, not a folder' if ckpt.exists() else 'not found'}; pass a folder written by `tesseract4d train` (RUN/final) "
                        f"or `tesseract4d train --export RUN --to DIR`")
    cfg_path = ckpt / INFERENCE_CONFIG_FILE
    if not cfg_path.is_file() or not (ckpt / TRANSFORMER_DIR / WEIGHTS_FILE).is_file():
        if (ckpt / "trainer_state.json").is_file():
            hint = " (a training checkpoint: export it with `tesseract4d train --export RUN`)"
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

    from tesseract4d.model.pipeline import make_scheduler

    folder = Path(checkpoint) / SCHEDULER_DIR
    if config["version"] == 1:
        return make_scheduler()
    if not (folder / SCHEDULER_CONFIG_FILE).is_file():
        raise UserError(f"{folder / SCHEDULER_CONFIG_FILE} is missing; re-export the checkpoint with `tesseract4d train --export RUN`")
    return FlowMatchEulerDiscreteScheduler.from_pretrained(folder)


def load_transformer(checkpoint: str | os.PathLike, preset, modality_channels: dict[str, int],
                     subfolder: str = TRANSFORMER_DIR):
    """The checkpoint's RGBDNTransformer (``from_pretrained``), checked against the preset and the
    codec's ``modality_channels`` first, so a mismatch says which setting differs. ``subfolder``
    GUIDE_DIR loads the autoguidance network instead; it may be smaller than the preset's backbone
    (its channels and text width must still fit)."""
    from tesseract4d.model.rgbdn_transformer import RGBDNTransformer

    folder = Path(checkpoint) / subfolder
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
        shape_only = subfolder == GUIDE_DIR  # a guide may have other layers, heads or widths
        mismatch = {k: (saved.get("backbone_config", {}).get(k), v) for k, v in preset.backbone.items()
                    if saved.get("backbone_config", {}).get(k) != v
                    and (not shape_only or k in GUIDE_MUST_MATCH)}
        if mismatch:
            raise UserError(f"{folder} does not match preset {preset.name!r}: "
                            + ", ".join(f"{k} is {a}, preset has {b}" for k, (a, b) in mismatch.items()))
    from safetensors import SafetensorError, safe_open

    try:  # the header lists every tensor's byte range: a truncated or garbled file fails here
        with safe_open(str(folder / WEIGHTS_FILE), "pt") as weights:
            weights.keys()
            in_8_bits = _in_8_bits(weights.metadata())
    except (SafetensorError, OSError) as e:
        raise UserError(f"{folder / WEIGHTS_FILE} is corrupt or truncated ({e}); re-export the checkpoint") from e
    try:
        if in_8_bits:  # `set-sampler --guide-bits 8`: not diffusers' layout, so built from the config
            model = RGBDNTransformer.from_config(RGBDNTransformer.load_config(folder)).float()
            model.load_state_dict(read_weights(folder / WEIGHTS_FILE)[0], strict=True)
        else:
            model = RGBDNTransformer.from_pretrained(folder).float()  # weights may be stored in float16
    except (RuntimeError, ValueError, OSError, TypeError) as e:
        raise UserError(f"{folder}: weights do not match the config of preset {preset.name!r} "
                        f"({str(e).splitlines()[0]} ...); re-export the checkpoint") from e
    return model.eval()


# What a guide network must share with the checkpoint's backbone to see the same tokens and text.
GUIDE_MUST_MATCH = ("patch_size", "patch_size_t", "text_embed_dim", "max_text_seq_length", "sample_width",
                    "sample_height", "sample_frames")
# The preset fields that only say how a checkpoint samples (the weights do not depend on them).
SAMPLER_FIELDS = ("num_steps", "text_guidance", "image_guidance", "guidance_min_sigma", "autoguidance",
                  "autoguidance_min_sigma", "static_tolerance", "draws")
# The preset fields of a noise-level interval (0: every step).
_INTERVAL_FIELDS = ("guidance_min_sigma", "autoguidance_min_sigma")


def check_sampler_settings(settings: dict) -> None:
    """UserError naming the flag when a sampler setting is out of range."""
    import math

    flags = {"num_steps": "--steps", "text_guidance": "--text-guidance", "image_guidance": "--image-guidance",
             "guidance_min_sigma": "--guidance-min-sigma", "autoguidance": "--autoguidance",
             "autoguidance_min_sigma": "--autoguidance-min-sigma", "static_tolerance": "--static-tolerance",
             "draws": "--draws"}
    for name, value in settings.items():
        if name not in SAMPLER_FIELDS:
            raise UserError(f"{name!r} is not a sampler setting (one of {', '.join(SAMPLER_FIELDS)})")
        if name in ("num_steps", "draws"):
            if int(value) != value or value < 1:
                what = "steps" if name == "num_steps" else "noise draws (1: a single draw)"
                raise UserError(f"{flags[name]} must be a whole number of {what} ≥ 1, got {value}")
        elif name in ("autoguidance", "static_tolerance"):
            if not math.isfinite(value) or value < 0:
                raise UserError(f"{flags[name]} must be a finite number ≥ 0 (0: off), got {value}")
        elif not math.isfinite(value) or value < 0 or (name not in _INTERVAL_FIELDS and value == 0):
            what = "≥ 0 (0: guidance at every step)" if name in _INTERVAL_FIELDS else "> 0 (1: no guidance)"
            raise UserError(f"{flags[name]} must be a finite number {what}, got {value}")


def _latent_lineage(config: dict) -> str | None:
    """The autoencoder a checkpoint's transformer was trained with (its latent space), by hash."""
    entry = config.get("autoencoder")
    return None if entry is None else entry.get("trained_with_hash", entry["hash"])


def check_guide(checkpoint: Path, config: dict, guide: Path) -> dict:
    """The guide checkpoint's inference config, after checking that its network sees the same inputs
    as ``checkpoint``'s: the same latent space (trained with the same autoencoder, or one whose
    encoder is bit for bit the same), resolution, frames and text encoder."""
    guide_config = read_inference_config(guide)
    for key in ("resolution", "num_frames", "text_encoder"):
        if guide_config.get(key) != config.get(key):
            raise UserError(f"--guide {guide} has {key} {guide_config.get(key)}, {checkpoint} has {config.get(key)}; "
                            f"a guide must be a checkpoint of the same data and text encoder")
    if ("autoencoder" in guide_config) != ("autoencoder" in config):
        raise UserError(f"--guide {guide} and {checkpoint} are not both latent checkpoints")
    if "autoencoder" in config and _latent_lineage(guide_config) != _latent_lineage(config):
        from tesseract4d.model.autoencoder import load_autoencoder
        from tesseract4d.model.latent_checkpoint import checkpoint_autoencoder, encoder_differences

        diff = encoder_differences(load_autoencoder(checkpoint_autoencoder(checkpoint, config["autoencoder"])),
                                   load_autoencoder(checkpoint_autoencoder(guide, guide_config["autoencoder"])))
        if diff:
            raise UserError(f"--guide {guide} works in another latent space than {checkpoint} ({'; '.join(diff[:2])}); "
                            f"take a checkpoint trained with the same autoencoder, e.g. an earlier one of its own run")
    return guide_config


def copy_checkpoint_files(checkpoint: Path, folder: Path, skip: tuple[str, ...] = ()) -> None:
    """Copy a checkpoint folder's files and folders into ``folder`` (a new checkpoint being written),
    all but its INFERENCE_CONFIG_FILE (the writer's to write), hidden files (an output marker) and
    the names in ``skip``."""
    import shutil

    for child in sorted(Path(checkpoint).iterdir()):
        if child.name == INFERENCE_CONFIG_FILE or child.name.startswith(".") or child.name in skip:
            continue
        (shutil.copytree if child.is_dir() else shutil.copy2)(child, Path(folder) / child.name)


def write_sampler_copy(checkpoint: str | os.PathLike, to: str | os.PathLike, settings: dict,
                       overwrite: bool = False, guide: str | os.PathLike | None = None,
                       guide_bits: int = 16) -> Path:
    """Write a copy of ``checkpoint`` into ``to`` (a new folder; the checkpoint is never changed) whose
    preset samples with ``settings`` (SAMPLER_FIELDS: steps, guidance scales, guidance interval,
    autoguidance, static compositing, noise draws), the weights byte for byte the same. ``guide``: a checkpoint whose transformer the
    copy carries as its autoguidance network (GUIDE_DIR), byte for byte, or with ``guide_bits`` 8 its
    matrices rounded to 8 bits per output row (half the bytes; a guide is a weaker network, and such a
    guide samples nearly as its float16 original on the held-out screen, docs/research/sampling.md). The
    previous settings and the source are recorded in INFERENCE_CONFIG_FILE under ``sampler_changed``;
    a model card is not copied (it describes the source)."""
    import shutil

    from tesseract4d.model.latent_checkpoint import own_autoencoder
    from tesseract4d.model.presets import preset_from_dict
    from tesseract4d.outputs import OutputDir

    if not settings and guide is None:
        raise UserError("nothing to change: give --steps, --text-guidance, --image-guidance, --guidance-min-sigma, "
                        "--autoguidance, --static-tolerance, --draws or --guide")
    check_sampler_settings(settings)
    if guide_bits not in (8, 16):
        raise UserError(f"--guide-bits must be 16 (the guide's weights as they are) or 8, got {guide_bits}")
    if guide_bits != 16 and guide is None:
        raise UserError("--guide-bits applies to the guide that --guide CKPT adds; give --guide too")
    checkpoint = Path(checkpoint)
    config = read_inference_config(checkpoint)
    preset = dict(config["preset"])
    saved = preset_from_dict(preset)  # settings an older checkpoint lacks read as their defaults
    previous = {name: getattr(saved, name) for name in settings}
    guide_config = None if guide is None else check_guide(checkpoint, config, Path(guide))
    if settings.get("autoguidance", saved.autoguidance) > 0 and guide is None and not (checkpoint / GUIDE_DIR).is_dir():
        raise UserError(f"autoguidance needs a weaker network of the same latent space: add --guide CKPT (e.g. an "
                        f"earlier checkpoint of {checkpoint}'s training run)")
    inputs = [checkpoint] + ([Path(guide)] if guide is not None else [])
    with OutputDir(to, "set-sampler", inputs=inputs, overwrite=overwrite, flag="--to") as tmp:
        # The guide folder, where a new guide replaces it, is written below.
        copy_checkpoint_files(checkpoint, tmp, skip=(MODEL_CARD_FILE,) + ((GUIDE_DIR,) if guide is not None else ()))
        preset.update(settings)
        change = {"source": str(checkpoint), "previous": previous, "new": dict(settings)}
        out = {**config, "preset": preset}
        if guide is not None:
            shutil.copytree(Path(guide) / TRANSFORMER_DIR, tmp / GUIDE_DIR)
            if guide_bits == 8:
                weights_to_int8(tmp / GUIDE_DIR / WEIGHTS_FILE)
            out["guide"] = {"source": str(guide), "digest": weights_digest(guide), "bits": guide_bits,
                            "training": guide_config.get("training")}
            if "blended" in guide_config:  # a guide made by scripts/blend_checkpoints.py: its recipe
                out["guide"]["blended"] = guide_config["blended"]
            change["guide"] = str(guide)
        out["sampler_changed"] = list(config.get("sampler_changed", [])) + [change]
        out = own_autoencoder(checkpoint, out, tmp)  # a copy elsewhere carries the autoencoder it shares
        (tmp / INFERENCE_CONFIG_FILE).write_text(json.dumps(out, indent=2))
    return Path(to)
