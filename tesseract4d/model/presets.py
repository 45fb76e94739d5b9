"""Model presets: one registry of named configurations of the same model, codec and training loop.

- ``tiny``: pixel space, 16 frames of 64x64, 4 transformer layers of 4x64 heads (7 M parameters),
  patches of 4x4 pixels x 4 frames (1,024 tokens: as fast as 8x8x1 patches, with twice the spatial
  resolution; 4x4x2 was 2.5x slower), MiniLM text; trains on a 2-core CPU in about an hour.
  ``tiny-128`` is the same at 128x128 with 8x8x4 patches (again 1,024 tokens).
- ``latent-128`` (the default): 16 frames of 128x128 in the latent space of the project's RGB-D-N
  autoencoder (``--autoencoder DIR``; 8x spatial compression, e.g. 32 channels): 2x2 latent patches,
  temporal patch 1, 1,024 tokens, tiny's width and depth, so a step costs about what tiny's does.
  The latent mixes the modalities, so it is one channel group with one projection and one head.
- ``cogvideox-5b``: latent space through ``AutoencoderKLCogVideoX``, backbone, VAE and T5 loaded from a
  local diffusers-format copy of CogVideoX-5B-I2V (``--pretrained DIR``); depth and normal get their
  own (zero-initialised) input projections and output heads copied from the RGB head.

A preset fixes the network's shape; training options (learning rate, batch, ...) are defaults that
the command line may override.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from tesseract4d.errors import UserError
from tesseract4d.model.model_space import DEFAULT_FAR_M, DEFAULT_NEAR_M

PIXEL = "pixel"
LATENT = "latent"
# The latent space of the project's own RGB-D-N autoencoder (model/autoencoder.py, --autoencoder DIR).
AUTOENCODER = "autoencoder"
# How the first frame is given to the network: repeated over all frames (pixel space: every token
# sees the first frame at its own position) or at frame 0 with zeros after it (CogVideoX-I2V's
# convention, which the pretrained weights expect).
CONDITION_REPEAT = "repeat"
CONDITION_FIRST = "first"


@dataclass(frozen=True)
class ModelPreset:
    name: str
    space: str  # PIXEL | LATENT | AUTOENCODER
    height: int  # pixels
    width: int
    num_frames: int  # frames per clip
    condition: str  # CONDITION_REPEAT | CONDITION_FIRST
    text_encoder: str  # "minilm" | "t5"
    max_text_tokens: int
    # CogVideoXTransformer3DModel keyword arguments (in/out channels are set by RGBDNTransformer).
    # Latent presets read the backbone from the pretrained folder instead.
    backbone: dict = field(default_factory=dict)
    near_m: float = DEFAULT_NEAR_M
    far_m: float = DEFAULT_FAR_M
    # training defaults
    lr: float = 3e-4
    warmup_steps: int = 200
    batch_size: int = 4
    ema_decay: float = 0.999
    grad_clip: float = 1.0
    text_dropout: float = 0.1
    image_dropout: float = 0.05
    # sampling defaults
    num_steps: int = 10
    text_guidance: float = 1.5
    image_guidance: float = 1.0
    # Guidance only at noise levels >= this (a guidance interval): lower-noise steps run one unguided
    # pass. 0 = every step guided.
    guidance_min_sigma: float = 0.0
    # Static compositing (static_composite.py): where the decoded clip stays within this of its frame 0
    # (model-space units, channels in [-1, 1]), the given first frame's pixels are put back. 0 = off.
    static_tolerance: float = 0.0
    # Noise draws per future (draw_choice.py): the kept one is the draw whose objects keep their
    # colours best. 1 = a single draw.
    draws: int = 1
    # History conditioning (long rollouts): a clip after the first continues from the last k frames of
    # the rollout so far, which fill the first k latent frames of its condition; it adds num_frames - k
    # new frames. 1 = today's rollout: each clip from the last frame of the one before. A model is
    # trained for its k (TrainConfig.history_frames, history_share, history_noise).
    history_frames: int = 1

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _tiny_backbone(size: int, patch_size: int, patch_size_t: int | None) -> dict:
    return dict(
        num_attention_heads=4, attention_head_dim=64, num_layers=4, time_embed_dim=256,
        text_embed_dim=384, max_text_seq_length=32,
        sample_width=size, sample_height=size, sample_frames=16,
        patch_size=patch_size, patch_size_t=patch_size_t, temporal_compression_ratio=1,
        use_rotary_positional_embeddings=True, use_learned_positional_embeddings=False,
    )


PRESETS: dict[str, ModelPreset] = {
    p.name: p
    for p in [
        ModelPreset("tiny", PIXEL, 64, 64, 16, CONDITION_REPEAT, "minilm", 32, backbone=_tiny_backbone(64, 4, 4)),
        ModelPreset("tiny-128", PIXEL, 128, 128, 16, CONDITION_REPEAT, "minilm", 32, backbone=_tiny_backbone(128, 8, 4)),
        # 128x128 x 16 frames through an 8x RGB-D-N autoencoder: 16x16 latents, 2x2 patches, temporal
        # patch 1 (a token never spans frames): 16 * 8 * 8 = 1,024 tokens, tiny's width and depth.
        ModelPreset("latent-128", AUTOENCODER, 128, 128, 16, CONDITION_REPEAT, "minilm", 32,
                    backbone=_tiny_backbone(16, 2, 1)),
        ModelPreset("cogvideox-5b", LATENT, 480, 720, 49, CONDITION_FIRST, "t5", 226,
                    lr=1e-4, warmup_steps=1000, batch_size=1, ema_decay=0.99, num_steps=50, text_guidance=7.5),
    ]
}


def get_preset(name: str) -> ModelPreset:
    if name not in PRESETS:
        raise UserError(f"unknown preset {name!r}; choose one of: {', '.join(PRESETS)}")
    return PRESETS[name]


# Sampler options of older checkpoints that this version no longer has (autoguidance, removed with its
# guide network: docs/research/removed_features.md). A saved preset with autoguidance 0 sampled without
# it and loads as before; any other scale is refused, since it sampled otherwise.
REMOVED_FIELDS = ("autoguidance", "autoguidance_min_sigma")


def without_removed_fields(d: dict) -> dict:
    """A saved preset dict without the removed options; a UserError when one was in use."""
    if d.get("autoguidance", 0.0) != 0.0:
        raise UserError(f"preset {d.get('name')!r} samples with autoguidance {d['autoguidance']}, which this "
                        f"tesseract4d no longer has (the guide network was removed); use a checkpoint that samples "
                        f"without it, e.g. one written by `tesseract4d set-sampler --autoguidance 0` in an older "
                        f"version, or that older version")
    return {k: v for k, v in d.items() if k not in REMOVED_FIELDS}


def preset_from_dict(d: dict) -> ModelPreset:
    """Rebuild a preset saved in a checkpoint (so a checkpoint keeps working if the registry changes).
    A UserError when it records a removed option in use (:func:`without_removed_fields`)."""
    known = {f.name for f in dataclasses.fields(ModelPreset)}
    return ModelPreset(**{k: v for k, v in without_removed_fields(d).items() if k in known})
