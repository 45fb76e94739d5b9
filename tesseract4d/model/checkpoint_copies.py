"""Copies of an inference checkpoint with one part changed: its default sampler settings
(``write_sampler_copy``, `tesseract4d checkpoint set-sampler`) or its decoder (``replace_decoder``,
`tesseract4d checkpoint swap-decoder`). The source is never changed; the copy is a new, owned folder.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import WEIGHTS_FILE as AE_WEIGHTS
from tesseract4d.model.autoencoder import ENCODER_PREFIXES, autoencoder_hash, read_autoencoder_config
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.model.checkpoint import (
    INFERENCE_CONFIG_FILE, MODEL_CARD_FILE, REMOVED_GUIDE_DIR, SCHEDULER_DIR, TRANSFORMER_DIR, check_sampler_settings,
    copy_checkpoint_files, read_inference_config,
)
from tesseract4d.model.latent_checkpoint import (
    AUTOENCODER_DIR, own_entry, checkpoint_autoencoder, encoder_differences, own_autoencoder,
)
from tesseract4d.model.presets import preset_from_dict, without_removed_fields
from tesseract4d.outputs import OutputDir


def write_sampler_copy(checkpoint: str | os.PathLike, to: str | os.PathLike, settings: dict,
                       overwrite: bool = False) -> Path:
    """Write a copy of ``checkpoint`` into ``to`` (a new folder; the checkpoint is never changed) whose
    preset samples with ``settings`` (SAMPLER_FIELDS: steps, guidance scales, guidance interval,
    static compositing, noise draws), the weights byte for byte the same. The previous settings and
    the source are recorded in INFERENCE_CONFIG_FILE under ``sampler_changed``; a model card is not
    copied (it describes the source)."""
    if not settings:
        raise UserError("nothing to change: give --steps, --text-guidance or --set NAME=VALUE (image_guidance, "
                        "guidance_min_sigma, static_tolerance, draws)")
    check_sampler_settings(settings)
    checkpoint = Path(checkpoint)
    config = read_inference_config(checkpoint)
    preset = without_removed_fields(config["preset"])
    saved = preset_from_dict(preset)  # settings an older checkpoint lacks read as their defaults
    previous = {name: getattr(saved, name) for name in settings}
    with OutputDir(to, "set-sampler", inputs=[checkpoint], overwrite=overwrite, flag="--to") as tmp:
        copy_checkpoint_files(checkpoint, tmp, skip=(MODEL_CARD_FILE, REMOVED_GUIDE_DIR))
        preset.update(settings)
        change = {"source": str(checkpoint), "previous": previous, "new": dict(settings)}
        out = {**{k: v for k, v in config.items() if k != "guide"}, "preset": preset}
        out["sampler_changed"] = list(config.get("sampler_changed", [])) + [change]
        out = own_autoencoder(checkpoint, out, tmp)  # a copy elsewhere carries the autoencoder it shares
        (tmp / INFERENCE_CONFIG_FILE).write_text(json.dumps(out, indent=2))
    return Path(to)


def replace_decoder(checkpoint: str | os.PathLike, autoencoder: str | os.PathLike, to: str | os.PathLike,
                    half: bool = False, overwrite: bool = False) -> Path:
    """Write a copy of the latent ``checkpoint`` into ``to`` whose autoencoder is ``autoencoder``: a
    decoder-only fine-tune of the checkpoint's own (``train-autoencoder --decoder-only``), so the
    transformer's latents are unchanged. Refused, naming what differs, when its encoder, latent
    statistics or architecture are not the checkpoint's. ``half`` stores the new decoder in float16
    (the encoder is copied as the checkpoint stores it, the transformer as it is)."""
    import torch  # deferred: torch and safetensors are heavy, the module's other readers need neither
    from safetensors.torch import load_file, save_file

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
            **own_entry(old), "hash": autoencoder_hash(dst), "source_dir": str(autoencoder),
            # The autoencoder the transformer was trained with: its encoder is this one's.
            "trained_with_hash": old.get("trained_with_hash", old["hash"]),
            "decoder_replaced": {"previous_hash": old["hash"], "source_hash": autoencoder_hash(autoencoder)},
        }
        (tmp / INFERENCE_CONFIG_FILE).write_text(json.dumps(config, indent=2))
    return Path(to)
