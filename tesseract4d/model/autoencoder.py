"""RGB-D-N autoencoder: per-frame continuous latents for the latent world model.

One frame in model space ``(7, H, W)`` (RGB, metric depth, normals; see ``model_space``) is
pixel-unshuffled by ``stem`` (``(7 * stem**2, H / stem, W / stem)``: cheap on a CPU, the pilot's
2x stem made 128² practical) and encoded by a diffusers ``AutoencoderKL`` into a latent
``(latent_channels, H / f, W / f)`` with ``f = spatial_compression``. Latents are normalised per
channel with statistics measured on training frames (``latent_mean``/``latent_std`` in the
config), so the diffusion model sees roughly unit-variance inputs. Decoding inverts the chain and
renormalises the normals to unit length (``model_space.renormalize_normals``).

A saved autoencoder is a folder::

    DIR/config.json          AutoencoderConfig (with the model space's depth range and latent statistics)
    DIR/model.safetensors    weights
    DIR/fidelity.json        the fidelity gate on held-out frames (written by the trainer)

Its identity is ``autoencoder_hash(DIR)`` (SHA-256 over config and weights): latent caches and
latent checkpoints record it and refuse to mix autoencoders.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F

from tesseract4d.errors import UserError
from tesseract4d.outputs import files_as_created
from tesseract4d.model.model_space import NUM_CHANNELS, ModelSpace, renormalize_normals

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
# The weights that make the latents, and the config fields the latents do not depend on: a decoder-only
# fine-tune (`train-autoencoder --decoder-only`) changes neither, so its latents are the init's, bit for bit.
ENCODER_PREFIXES = ("vae.encoder.", "vae.quant_conv.")
DECODER_FIELDS = ("name", "first_frame_injection")
# A config field of older autoencoders that this version no longer has: a lighter decoder than the
# encoder (docs/research/removed_features.md). Saved as null it meant the same depth, and reads as before.
REMOVED_DECODER_DEPTH = "decoder_layers_per_block"
FIDELITY_FILE = "fidelity.json"
FORMAT = "tesseract4d-autoencoder"


@dataclass
class AutoencoderConfig:
    """Architecture of the RGB-D-N autoencoder; saved as DIR/config.json so a folder rebuilds itself."""

    name: str = "ae-f8c16"
    stem: int = 2  # pixel-unshuffle factor in front of the KL autoencoder
    block_out_channels: tuple[int, ...] = (32, 64, 128)  # one 2x downsample between consecutive blocks
    layers_per_block: int = 1
    latent_channels: int = 16
    norm_num_groups: int = 32
    mid_attention: bool = False  # self-attention in the bottleneck (costly on a CPU)
    # The decoder also reads the clip's first frame (first_frame_decoder.INJECTIONS, e.g. "attention"); None: it does not.
    first_frame_injection: str | None = None
    height: int = 128
    width: int = 128
    model_space: dict = field(default_factory=lambda: ModelSpace().to_dict())
    # Per-channel statistics of the posterior means on training frames; None until measured.
    latent_mean: list[float] | None = None
    latent_std: list[float] | None = None

    @property
    def spatial_compression(self) -> int:
        return self.stem * 2 ** (len(self.block_out_channels) - 1)

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """(channels, height, width) of one frame's latent."""
        f = self.spatial_compression
        return (self.latent_channels, self.height // f, self.width // f)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["block_out_channels"] = list(self.block_out_channels)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "AutoencoderConfig":
        lighter = d.get(REMOVED_DECODER_DEPTH)
        if lighter is not None and lighter != d.get("layers_per_block", cls.layers_per_block):
            raise UserError(f"autoencoder {d.get('name')!r} has a decoder of {lighter} layers per block (encoder: "
                            f"{d.get('layers_per_block')}); this tesseract4d builds decoders as deep as their encoder: "
                            f"use an older tesseract4d for it, or train one with `tesseract4d train-autoencoder`")
        known = {f.name for f in dataclasses.fields(cls)}
        d = {k: v for k, v in d.items() if k in known}
        d["block_out_channels"] = tuple(d["block_out_channels"])
        return cls(**d)


AUTOENCODER_PRESETS: dict[str, AutoencoderConfig] = {
    # 8x compression, 16 channels: 128² -> 16x16x16 per frame (the pilot's best at equal time);
    # 2.6 M parameters, about 0.5 steps/s at batch 8 on a shared 2-core AVX512-BF16 CPU.
    "ae-f8c16": AutoencoderConfig(name="ae-f8c16"),
    # 8x compression, 32 channels: more room for depth/normal detail at the same spatial grid.
    "ae-f8c32": AutoencoderConfig(name="ae-f8c32", latent_channels=32),
    # 4x compression, 8 channels (2.5 M parameters): 128² -> 32x32x8 per frame, as many numbers as ae-f8c32's 16x16x32, but a
    # 4-pixel cube spans one latent cell instead of a quarter of one (a GPU lever, docs/research/first_frame_decoder.md).
    "ae-f4c8": AutoencoderConfig(name="ae-f4c8", block_out_channels=(64, 128), latent_channels=8),
    # Twice as wide (10 M parameters, about 5x slower per step here): for machines with more cores.
    "ae-f8c16-wide": AutoencoderConfig(name="ae-f8c16-wide", block_out_channels=(64, 128, 256)),
    # Tests only: seconds to build and run.
    "ae-test": AutoencoderConfig(name="ae-test", block_out_channels=(8, 8, 16), latent_channels=4,
                                 norm_num_groups=4, height=32, width=32),
}


def get_autoencoder_preset(name: str) -> AutoencoderConfig:
    if name not in AUTOENCODER_PRESETS:
        raise UserError(f"unknown autoencoder preset {name!r}; choose from {', '.join(AUTOENCODER_PRESETS)}")
    return dataclasses.replace(AUTOENCODER_PRESETS[name])


class _Fp32Conv2d(torch.nn.Conv2d):
    """A ``Conv2d`` that runs in fp32 even inside a bf16 autocast region (same weights and keys).

    The decoder's last convolution writes metric depth and normals: in bf16 its output steps are
    coarse enough to turn a decoded normal by 1.6° on average (1.4 mm of depth), against 0.3° with
    this one layer in fp32, which costs nothing measurable (benchmarks/bench_latent.py).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, enabled=False):
            return super().forward(x.float())


def _to_channels_last(module: torch.nn.Module, args: tuple) -> tuple:
    """Forward pre-hook: the module's first input in channels-last memory format."""
    return (args[0].contiguous(memory_format=torch.channels_last), *args[1:])


class RGBDNAutoencoder(torch.nn.Module):
    """Per-frame RGB-D-N autoencoder on ``diffusers.AutoencoderKL`` (see the module docstring)."""

    def __init__(self, config: AutoencoderConfig):
        super().__init__()
        from diffusers import AutoencoderKL

        self.config = config
        self.model_space = ModelSpace(**config.model_space)
        n = len(config.block_out_channels)
        channels = NUM_CHANNELS * config.stem**2
        self.vae = AutoencoderKL(
            in_channels=channels, out_channels=channels,
            down_block_types=("DownEncoderBlock2D",) * n, up_block_types=("UpDecoderBlock2D",) * n,
            block_out_channels=tuple(config.block_out_channels), layers_per_block=config.layers_per_block,
            latent_channels=config.latent_channels, norm_num_groups=config.norm_num_groups,
            sample_size=config.height // config.stem, mid_block_add_attention=config.mid_attention,
        )
        self.vae.decoder.conv_out.__class__ = _Fp32Conv2d  # a subclass: deep copies (EMA) keep it
        # The decoder runs channels-first at the latent resolution and channels-last from its first
        # upsampling on: oneDNN's convolutions skip layout reorders on channels-last activations
        # (a 16-frame decode about 15 % faster), but bf16 GroupNorm on channels-last 16x16 maps of
        # 128 channels takes 19x the time of channels-first (1.9 against 0.1 ms a call): switching
        # after them decodes a 16-frame clip in 0.105 s instead of 0.117 (bf16; fp32 unchanged).
        # Same outputs to bf16 rounding.
        upsamplers = self.vae.decoder.up_blocks[0].upsamplers
        if upsamplers:
            upsamplers[0].register_forward_pre_hook(_to_channels_last)
        self._set_stats(config.latent_mean, config.latent_std)

    def _set_stats(self, mean: list[float] | None, std: list[float] | None) -> None:
        c = self.config.latent_channels
        device = next(self.vae.parameters()).device  # where the model already is (e.g. a GPU)
        m = torch.tensor(mean, dtype=torch.float32) if mean is not None else torch.zeros(c)
        s = torch.tensor(std, dtype=torch.float32) if std is not None else torch.ones(c)
        self.register_buffer("latent_mean", m.view(1, c, 1, 1).to(device), persistent=False)
        self.register_buffer("latent_std", s.view(1, c, 1, 1).to(device), persistent=False)

    def set_latent_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Record per-channel latent statistics (into the config too, so they are saved)."""
        self.config.latent_mean = [float(v) for v in mean.flatten()]
        self.config.latent_std = [float(v) for v in std.flatten().clamp_min(1e-4)]
        self._set_stats(self.config.latent_mean, self.config.latent_std)

    def _check(self, x: torch.Tensor) -> None:
        if x.ndim != 4 or x.shape[1] != NUM_CHANNELS or tuple(x.shape[-2:]) != (self.config.height, self.config.width):
            raise ValueError(f"expected frames (n, {NUM_CHANNELS}, {self.config.height}, {self.config.width}), "
                             f"got {tuple(x.shape)}")

    @property
    def device(self) -> torch.device:
        return self.latent_mean.device

    # ------------------------------------------------------------------ training-level API
    def posterior(self, x: torch.Tensor):
        """Frames (n, 7, H, W) model space (on any device) -> the diagonal Gaussian posterior over
        raw latents, on the model's device."""
        self._check(x)
        h = F.pixel_unshuffle(x.to(self.device), self.config.stem)  # (n, 7 * s², H / s, W / s)
        return self.vae.encode(h).latent_dist

    def decode_raw(self, z_raw: torch.Tensor) -> torch.Tensor:
        """Raw (unnormalised) latents (n, C, h, w) -> frames (n, 7, H, W), normals not yet unit."""
        h = self.vae.decode(z_raw.contiguous()).sample  # channels-last from the first upsampling (__init__)
        return F.pixel_shuffle(h, self.config.stem)

    # ------------------------------------------------------------------ latent API
    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Frames (n, 7, H, W) model space -> normalised latents (n, C, H/f, W/f) (posterior means)."""
        z = self.posterior(x).mean
        return (z - self.latent_mean) / self.latent_std

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Normalised latents (n, C, h, w) on any device -> fp32 frames (n, 7, H, W) in [-1, 1] on the
        model's device, normals unit length.

        Inside a bf16 autocast region the decoder runs in bf16 except its last convolution."""
        x = self.decode_raw(z.to(self.device) * self.latent_std + self.latent_mean).float().clamp(-1.0, 1.0)
        return renormalize_normals(x)

    def encode_clips(self, x: torch.Tensor, chunk: int = 16) -> torch.Tensor:
        """Clips (b, t, 7, H, W) -> latents (b, t, C, h, w), ``chunk`` frames at a time."""
        b, t = x.shape[:2]
        flat = x.reshape(b * t, *x.shape[2:])  # (b*t, 7, H, W)
        z = torch.cat([self.encode(flat[i:i + chunk]) for i in range(0, b * t, chunk)])
        return z.reshape(b, t, *z.shape[1:])

    def decode_clips(self, z: torch.Tensor, chunk: int = 16) -> torch.Tensor:
        """Latents (b, t, C, h, w) -> clips (b, t, 7, H, W)."""
        b, t = z.shape[:2]
        flat = z.reshape(b * t, *z.shape[2:])  # (b*t, C, h, w)
        x = torch.cat([self.decode(flat[i:i + chunk]) for i in range(0, b * t, chunk)])
        return x.reshape(b, t, *x.shape[1:])


# --------------------------------------------------------------------------- folders


def save_autoencoder(model: RGBDNAutoencoder, folder: str | os.PathLike, state_dict: dict | None = None) -> Path:
    """Write config.json + model.safetensors into ``folder`` (created; the caller makes it atomic)."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sd = state_dict if state_dict is not None else model.state_dict()
    save_file({k: v.detach().cpu().contiguous() for k, v in sd.items()}, str(folder / WEIGHTS_FILE))
    files_as_created(folder / WEIGHTS_FILE)  # safetensors writes 0600
    (folder / CONFIG_FILE).write_text(json.dumps({"format": FORMAT, **model.config.to_dict()}, indent=2))
    return folder


def read_autoencoder_config(folder: str | os.PathLike) -> AutoencoderConfig:
    folder = Path(folder)
    path = folder / CONFIG_FILE
    if not path.is_file() or not (folder / WEIGHTS_FILE).is_file():
        raise UserError(f"{folder} is not a tesseract4d autoencoder (no {CONFIG_FILE} + {WEIGHTS_FILE}); "
                        f"train one with `tesseract4d train-autoencoder --out RUN` and use RUN/autoencoder")
    d = json.loads(path.read_text())
    if d.get("format") != FORMAT:
        raise UserError(f"{path} is not a tesseract4d autoencoder config (format {d.get('format')!r})")
    return AutoencoderConfig.from_dict(d)


def _weights_damaged(folder: Path, why: str) -> UserError:
    return UserError(f"autoencoder weights {folder / WEIGHTS_FILE} are corrupt or truncated ({why}); copy them again "
                     f"from the run that wrote them (RUN/autoencoder), or train them again with "
                     f"`tesseract4d train-autoencoder`")


def check_weights_whole(folder: str | os.PathLike) -> None:
    """UserError when a saved autoencoder's safetensors file is not whole: its header unreadable, or the
    file shorter or longer than the tensors the header lists. Reads the header only, so the identity
    hash of a cut-off copy is never taken as that of another autoencoder."""
    path = Path(folder) / WEIGHTS_FILE
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
            if len(head) < 8:
                raise _weights_damaged(Path(folder), f"{size} bytes, no safetensors header")
            n = int.from_bytes(head, "little")
            if n > size - 8:
                raise _weights_damaged(Path(folder), f"the header announces {n} bytes, the file has {size}")
            header = json.loads(f.read(n))
        end = max((int(v["data_offsets"][1]) for k, v in header.items() if k != "__metadata__"), default=0)
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError) as e:
        raise _weights_damaged(Path(folder), f"unreadable header: {e}") from None
    if 8 + n + end != size:
        raise _weights_damaged(Path(folder), f"{size} bytes where its header lists {8 + n + end}")


def load_weights(folder: Path) -> dict:
    """A saved autoencoder's tensors; a UserError naming the file when it is not a whole safetensors file."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = folder / WEIGHTS_FILE
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as e:
        raise UserError(f"autoencoder weights {path} are corrupt or truncated ({e}); copy them again from the run that "
                        f"wrote them (RUN/autoencoder), or train them again with `tesseract4d train-autoencoder`") from e


def autoencoder_hash(folder: str | os.PathLike) -> str:
    """SHA-256 (hex, 16 chars) of a saved autoencoder's config and weights: its identity."""
    folder = Path(folder)
    read_autoencoder_config(folder)
    check_weights_whole(folder)
    h = hashlib.sha256()
    for name in (CONFIG_FILE, WEIGHTS_FILE):
        with open(folder / name, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:16]


def latents_hash(folder: str | os.PathLike) -> str:
    """SHA-256 (hex, 16 chars) of what a saved autoencoder's latents depend on: its config but for
    ``DECODER_FIELDS`` (the latent statistics included) and its encoder weights as float32. Equal for an
    autoencoder and a decoder-only fine-tune of it, so a latent cache outlives a decoder swap."""
    folder = Path(folder)
    config = read_autoencoder_config(folder).to_dict()
    h = hashlib.sha256(json.dumps({k: v for k, v in config.items() if k not in DECODER_FIELDS}, sort_keys=True).encode())
    weights = load_weights(folder)
    for key in sorted(weights):
        if key.startswith(ENCODER_PREFIXES):
            h.update(key.encode())
            h.update(weights[key].float().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]
