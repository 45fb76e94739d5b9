"""Codecs between model-space pixels and the space the transformer works in.

Model-space pixel clips are ``(b, t, 7, H, W)`` (model_space.py). The ``tiny`` presets work on them
directly (``PixelCodec``); ``cogvideox-5b`` works on the latents of ``AutoencoderKLCogVideoX``
(``VaeCodec``): rgb, depth (repeated to 3 channels) and normal are encoded separately, each to
``latent_channels`` channels, and stacked on channels: ``(b, t', 3 * latent_channels, h, w)``.

Also here: how the first frame (or a clip's history frames) becomes the transformer's ``condition`` input.
"""

from __future__ import annotations

import torch

from tesseract4d.model.model_space import MODALITIES, MODALITY_CHANNELS, channel_slices
from tesseract4d.model.presets import CONDITION_REPEAT


class PixelCodec:
    """Identity codec: the network sees model-space pixels."""

    temporal_compression = 1

    def __init__(self) -> None:
        self.modality_channels = dict(MODALITY_CHANNELS)

    def to(self, device: torch.device | str) -> "PixelCodec":
        return self

    def num_latent_frames(self, num_frames: int) -> int:
        return num_frames

    def encode(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        return x  # (b, t, 7, h, w)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return z


class VaeCodec:
    """Per-modality encoding through a CogVideoX VAE (frozen)."""

    def __init__(self, vae) -> None:
        self.vae = vae.eval().requires_grad_(False)
        self.scaling = float(vae.config.scaling_factor)
        self.temporal_compression = int(vae.config.temporal_compression_ratio)
        lc = int(vae.config.latent_channels)
        self.modality_channels = {name: lc for name in MODALITIES}

    def to(self, device: torch.device | str) -> "VaeCodec":
        self.vae.to(device)
        return self

    def num_latent_frames(self, num_frames: int) -> int:
        if (num_frames - 1) % self.temporal_compression:
            raise ValueError(f"a latent clip needs 1 + {self.temporal_compression}k frames, got {num_frames}")
        return (num_frames - 1) // self.temporal_compression + 1

    @torch.no_grad()
    def encode(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(b, t, 7, H, W) model-space pixels -> (b, t', 3*lc, h, w) scaled latents."""
        parts = []
        for s in channel_slices().values():
            v = x[:, :, s]
            if v.shape[2] == 1:
                v = v.expand(-1, -1, 3, -1, -1)
            v = v.permute(0, 2, 1, 3, 4).to(self.vae.dtype)  # (b, 3, t, H, W)
            z = self.vae.encode(v).latent_dist.sample(generator) * self.scaling  # (b, lc, t', h, w)
            parts.append(z.permute(0, 2, 1, 3, 4).float())
        return torch.cat(parts, dim=2)

    @torch.no_grad()
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(b, t', 3*lc, h, w) latents -> (b, t, 7, H, W) model-space pixels."""
        lc = self.modality_channels["rgb"]
        out = []
        for i, name in enumerate(MODALITIES):
            zi = z[:, :, i * lc:(i + 1) * lc].permute(0, 2, 1, 3, 4) / self.scaling  # (b, lc, t', h, w)
            v = self.vae.decode(zi.to(self.vae.dtype)).sample.float().permute(0, 2, 1, 3, 4)  # (b, t, 3, H, W)
            out.append(v.mean(dim=2, keepdim=True) if MODALITY_CHANNELS[name] == 1 else v)
        return torch.cat(out, dim=2)


def make_condition(first: torch.Tensor, num_latent_frames: int, mode: str) -> torch.Tensor:
    """The condition (b, t', c, h, w) from the encoded given frames ``first`` (b, k, c, h, w): one first
    frame (k = 1), or the k history frames a clip continues from (``ModelPreset.history_frames``), which
    fill the condition's first k latent frames. After them: the last given frame repeated (``repeat``),
    or zeros (``first``, CogVideoX-I2V)."""
    k = first.shape[1]
    if not 1 <= k <= num_latent_frames:
        raise ValueError(f"{k} given frames do not fit a condition of {num_latent_frames} latent frames")
    if mode == CONDITION_REPEAT:
        if k == 1:
            return first.expand(-1, num_latent_frames, -1, -1, -1).contiguous()
        return torch.cat([first, first[:, -1:].expand(-1, num_latent_frames - k, -1, -1, -1)], dim=1)
    pad = first.new_zeros(first.shape[0], num_latent_frames - k, *first.shape[2:])
    return torch.cat([first, pad], dim=1)


class AutoencoderCodec:
    """The project's RGB-D-N autoencoder (``autoencoder.py``, frozen): per-frame latents.

    Its latent mixes the modalities, so the network sees one joint channel group ``"latent"``:
    ``(b, t, 7, H, W)`` model-space pixels <-> ``(b, t, C, H/f, W/f)`` normalised latents.
    """

    temporal_compression = 1

    def __init__(self, autoencoder, autoencoder_hash: str = "") -> None:
        # channels_last weights: the CPU's convolutions (oneDNN) decode a 16-frame 128² clip about a
        # quarter faster, with outputs equal to about 1e-5 (benchmarks/bench_latent.py).
        self.autoencoder = autoencoder.eval().requires_grad_(False).to(memory_format=torch.channels_last)
        self.autoencoder_hash = autoencoder_hash
        self.spatial_compression = autoencoder.config.spatial_compression
        self.modality_channels = {"latent": autoencoder.config.latent_channels}

    def to(self, device: torch.device | str) -> "AutoencoderCodec":
        self.autoencoder.to(device)
        return self

    def num_latent_frames(self, num_frames: int) -> int:
        return num_frames

    @torch.no_grad()
    def encode(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(b, t, 7, H, W) -> (b, t, C, h, w) (posterior means: deterministic)."""
        return self.autoencoder.encode_clips(x.float())

    @property
    def reads_first_frame(self) -> bool:
        """Whether the decoder also reads each clip's first frame (first_frame_decoder.py)."""
        return self.autoencoder.config.first_frame_injection is not None

    @torch.no_grad()
    def decode(self, z: torch.Tensor, first_frame: torch.Tensor | None = None) -> torch.Tensor:
        """(b, t, C, h, w) -> (b, t, 7, H, W), normals renormalised. ``first_frame`` (b, 7, H, W) model
        space: the clips' given first frames, for a decoder that reads them (without, it reads each
        clip's frame 0 as decoded from its latent)."""
        if self.reads_first_frame:
            return self.autoencoder.decode_clips(z.float(), first_frame=first_frame)
        return self.autoencoder.decode_clips(z.float())
