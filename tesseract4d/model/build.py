"""Build a preset's components: transformer, codec and text encoder (fresh, or from a local folder).

Latent presets read a local diffusers-format model folder (``--pretrained DIR``) laid out as
CogVideoX-5B-I2V is: ``transformer/``, ``vae/``, ``text_encoder/``, ``tokenizer/``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from tesseract4d.errors import UserError
from tesseract4d.model.presets import AUTOENCODER, LATENT, PIXEL, ModelPreset
from tesseract4d.model.text_encoder import TextEncoder
from tesseract4d.model.codec import AutoencoderCodec, PixelCodec, VaeCodec
from tesseract4d.model.autoencoder import autoencoder_hash
from tesseract4d.model.autoencoder_loading import load_autoencoder

# Keys of a plain CogVideoX transformer -> keys inside RGBDNTransformer.
_KEY_MAP = (("patch_embed.proj.", "backbone.patch_embed.proj.projs.rgb."), ("proj_out.", "backbone.proj_out.heads.rgb."))


def _require_pretrained(preset: ModelPreset, pretrained_dir: str | os.PathLike | None, part: str) -> Path:
    if pretrained_dir is None:
        raise UserError(f"preset {preset.name!r} needs a local copy of CogVideoX-5B-I2V: pass --pretrained DIR "
                        f"(a diffusers model folder with transformer/, vae/, text_encoder/, tokenizer/)")
    folder = Path(pretrained_dir) / part
    if not folder.is_dir():
        raise UserError(f"{folder} not found: --pretrained must be a diffusers model folder with transformer/, vae/, "
                        f"text_encoder/ and tokenizer/ (e.g. a local copy of THUDM/CogVideoX-5b-I2V)")
    return folder


_TEXT_ENCODERS: dict[tuple, object] = {}


def build_text_encoder(preset: ModelPreset, pretrained_dir=None, device="cpu"):
    """The preset's frozen text encoder; one instance per process and configuration (it is only read)."""
    path = _require_pretrained(preset, pretrained_dir, "text_encoder").parent if preset.text_encoder == "t5" else None
    key = (preset.text_encoder, preset.max_text_tokens, str(path), str(device))
    if key not in _TEXT_ENCODERS:
        _TEXT_ENCODERS[key] = TextEncoder(preset.text_encoder, preset.max_text_tokens, path=path, device=device)
    return _TEXT_ENCODERS[key]


def build_codec(preset: ModelPreset, pretrained_dir=None, autoencoder=None):
    """The preset's codec; latent presets of the project's autoencoder need its folder (``autoencoder``)."""
    if preset.space == PIXEL:
        return PixelCodec()
    if preset.space == AUTOENCODER:
        if autoencoder is None:
            raise UserError(f"preset {preset.name!r} needs its RGB-D-N autoencoder: pass --autoencoder DIR "
                            f"(RUN/autoencoder of `tesseract4d train-autoencoder`)")
        return AutoencoderCodec(load_autoencoder(autoencoder), autoencoder_hash(autoencoder))
    from diffusers import AutoencoderKLCogVideoX

    return VaeCodec(AutoencoderKLCogVideoX.from_pretrained(_require_pretrained(preset, pretrained_dir, "vae")))


def build_transformer(preset: ModelPreset, codec, pretrained_dir=None):
    """A fresh RGBDNTransformer for training: random (pixel presets) or the pretrained CogVideoX
    backbone with new zero-initialised depth/normal projections and heads copied from RGB (latent)."""
    # deferred: imports diffusers (heavy)
    from tesseract4d.model.rgbdn_transformer import RGBDNTransformer

    if preset.space in (PIXEL, AUTOENCODER):
        model = RGBDNTransformer(dict(preset.backbone), dict(codec.modality_channels))
        model.zero_output_heads()  # start as "copy the first frame", the static-world baseline
        return model
    if preset.space != LATENT:
        raise ValueError(f"unknown model space {preset.space!r}")
    from diffusers import CogVideoXTransformer3DModel

    folder = _require_pretrained(preset, pretrained_dir, "transformer")
    cfg = json.loads((folder / "config.json").read_text())
    c = codec.modality_channels["rgb"]
    if cfg.get("in_channels") != 2 * c or cfg.get("out_channels") != c:
        raise UserError(f"{folder} is not an image-to-video CogVideoX transformer for {c}-channel latents "
                        f"(in_channels {cfg.get('in_channels')}, out_channels {cfg.get('out_channels')}; expected {2 * c}, {c})")
    backbone = {k: v for k, v in cfg.items() if not k.startswith("_") and k not in ("in_channels", "out_channels")}
    model = RGBDNTransformer(backbone, dict(codec.modality_channels))
    pretrained = CogVideoXTransformer3DModel.from_pretrained(folder).state_dict()
    state = {}
    for key, value in pretrained.items():
        for old, new in _KEY_MAP:
            if key.startswith(old):
                state[new + key[len(old):]] = value
                break
        else:
            state["backbone." + key] = value
    missing, unexpected = model.load_state_dict(state, strict=False)
    new_parts = [k for k in missing if ".projs.rgb." not in k and ".heads.rgb." not in k
                 and (".projs." in k or ".heads." in k)]
    if unexpected or len(new_parts) != len(missing):
        raise UserError(f"{folder} does not match the CogVideoX structure: missing {sorted(set(missing) - set(new_parts))[:5]}, "
                        f"unexpected {unexpected[:5]}")
    model.copy_rgb_head_to_other_heads()
    return model
