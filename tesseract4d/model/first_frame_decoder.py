"""A decoder that reads the clip's first frame: the latent says *where* things are, frame 0 *what* they look like.

The shipped per-frame decoder redraws every object from its latent cell alone; at 8x compression a
4-pixel cube is a fraction of one cell and is lost (the truth's own round trip drops an object in one
tabletop frame in five). Every prediction starts from a given RGB-D-N frame holding each object's exact
look, so this decoder is given that frame too:

1. the *frozen* encoder of the same autoencoder reads frame 0 and its features are kept at every decoder
   scale (``reference_features``): the pixel-unshuffled frame and the first down block's output at the
   stem's resolution (``H/s``), the second down block's at ``H/2s``, the last block's and the bottleneck's
   at the latent resolution ``H/f``;
2. after the decoder's mid block and after each up block, an *injection* adds what it reads from those
   features to the decoder's activations (``h <- h + inject(h, ref)``):

   - ``concat``: two convolutions over the channel concatenation ``[GroupNorm(h), ref]`` (3x3 each, the
     second zero-initialised): a skip path from the encoder, one latent cell of reach per layer;
   - ``attention``: at the two coarse scales, single-head cross-attention from the decoder's positions
     (queries) to all positions of frame 0's features (keys, values), both with the same 2D sine-cosine
     positions, so a moved object can take its look from where it stood in frame 0; the output
     projection is zero-initialised; the two finest scales (4096 positions, too dear to attend over on
     a CPU) use ``concat``.

With ``+pixels`` (``attention+pixels``...) one more injection acts in the output space itself, on the decoder's
pixel-unshuffled output ``y`` (``7 s²`` channels at ``H/s``): ``y <- y + conv(silu(conv([y, frame 0 unshuffled,
norm(h)])))``, the last convolution zero-initialised: copying a pixel of the given frame is then one linear map,
where the other injections must pass it through the shipped decoder's frozen output head.

With ``+copy`` (``attention+copy``...) that skip also holds a *copy term*: ``y <- y + g * (pixels - y) + ...``
with the gate ``g = copy(hidden)`` a zero-initialised 1x1 convolution (one gate per output channel and
position) of the skip's hidden layer. Where ``g`` reaches 1 the output is frame 0's pixel exactly, so copying
the still scene (and an object that has not moved) needs one gate, not a learnt identity through two 3x3
convolutions; where something changed the gate stays at 0 and the latent's decoding stands.

Every injection's last layer starts at zero, so a fresh ``FirstFrameAutoencoder`` initialised from a
shipped autoencoder decodes exactly as it does (``tests/test_first_frame_decoder.py`` checks this).
The encoder, its config and the latent statistics are the shipped ones, untouched: the latents are the
same bit for bit (``autoencoder.latents_hash``), so a latent checkpoint keeps its transformer and takes
this decoder with ``tesseract4d swap-decoder`` (which refuses an autoencoder that encodes differently).

Decoding needs the first frame, ``(n, 7, H, W)`` in model space: ``decode_clips(z, first_frame)``. When
none is given (a caller that only has latents), frame 0 of the clip decoded by the latent alone stands
in for it, and the docstring of every such call site says so.

Its config is the autoencoder's with ``first_frame_injection`` set (one of ``INJECTIONS``);
``autoencoder_loading.load_autoencoder`` builds this class for such a folder, so checkpoints load it unchanged.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import AutoencoderConfig, RGBDNAutoencoder
from tesseract4d.model.model_space import NUM_CHANNELS, renormalize_normals

INJECTIONS = ("concat", "attention", "concat+pixels", "attention+pixels", "concat+copy", "attention+copy")
PIXEL_SKIP = "+pixels"
# "+copy": the output-space skip of "+pixels" plus a gated copy of the given frame (``PixelSkip``'s ``copy``).
COPY_SKIP = "+copy"
OUTPUT_SPACE_SKIPS = (PIXEL_SKIP, COPY_SKIP)
# Weight names of the first-frame path (everything a first-frame fine-tune adds to a shipped autoencoder).
FIRST_FRAME_PREFIX = "first_frame."
# Width of the cross-attention's queries and keys.
ATTENTION_DIM = 64


def _zero(module: torch.nn.Module) -> torch.nn.Module:
    for p in module.parameters():
        torch.nn.init.zeros_(p)
    return module


def _groups(channels: int, wanted: int) -> int:
    """The largest group count <= wanted that divides ``channels``."""
    g = min(wanted, channels)
    while channels % g:
        g -= 1
    return g


def sincos_positions(height: int, width: int, dim: int, device=None) -> torch.Tensor:
    """(height * width, dim) 2D sine-cosine positions (half the channels for y, half for x)."""
    quarter = dim // 4
    freqs = torch.exp(-math.log(1000.0) * torch.arange(quarter, device=device, dtype=torch.float32) / quarter)
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                            torch.arange(width, device=device, dtype=torch.float32), indexing="ij")
    parts = []
    for coord in (ys.flatten(), xs.flatten()):
        angles = coord[:, None] * freqs[None]  # (hw, quarter)
        parts += [angles.sin(), angles.cos()]
    return torch.cat(parts, dim=1)  # (hw, 4 * quarter)


class ConcatInjection(torch.nn.Module):
    """``h + conv(silu(conv([norm(h), ref])))`` with the last convolution zero-initialised."""

    def __init__(self, channels: int, ref_channels: int, groups: int):
        super().__init__()
        self.norm = torch.nn.GroupNorm(_groups(channels, groups), channels)
        self.conv_in = torch.nn.Conv2d(channels + ref_channels, channels, 3, padding=1)
        self.conv_out = _zero(torch.nn.Conv2d(channels, channels, 3, padding=1))

    def forward(self, h: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """h (n, c, y, x) decoder activations; ref (n, r, y, x) frame 0's features for each of the n frames."""
        x = torch.cat([self.norm(h), ref.to(h.dtype)], dim=1)
        return h + self.conv_out(F.silu(self.conv_in(x)))


class AttentionInjection(torch.nn.Module):
    """``h + proj(softmax(q k^T / sqrt(d)) v)``: every decoder position attends to every position of
    frame 0's features; queries and keys carry the same 2D positions; ``proj`` is zero-initialised."""

    def __init__(self, channels: int, ref_channels: int, groups: int, dim: int = ATTENTION_DIM):
        super().__init__()
        self.dim = dim
        self.norm = torch.nn.GroupNorm(_groups(channels, groups), channels)
        self.ref_norm = torch.nn.GroupNorm(_groups(ref_channels, groups), ref_channels)
        self.to_q = torch.nn.Conv2d(channels, dim, 1)
        self.to_k = torch.nn.Conv2d(ref_channels, dim, 1)
        self.to_v = torch.nn.Conv2d(ref_channels, channels, 1)
        self.proj = _zero(torch.nn.Conv2d(channels, channels, 1))

    def forward(self, h: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        n, c, y, x = h.shape
        ref = self.ref_norm(ref.to(h.dtype))
        pos = sincos_positions(y, x, self.dim, h.device).to(h.dtype)  # (yx, d)
        q = self.to_q(self.norm(h)).flatten(2).transpose(1, 2) + pos  # (n, yx, d)
        k = self.to_k(ref).flatten(2).transpose(1, 2) + pos  # (n, yx, d)
        v = self.to_v(ref).flatten(2).transpose(1, 2)  # (n, yx, c)
        out = F.scaled_dot_product_attention(q[:, None], k[:, None], v[:, None])[:, 0]  # (n, yx, c)
        return h + self.proj(out.transpose(1, 2).reshape(n, c, y, x))


class PixelSkip(torch.nn.Module):
    """``y + conv(silu(conv([y, pixels, norm(h)])))`` in the output space (the last convolution zero-initialised):
    y, pixels (n, 7 s², H/s, W/s) the decoder's output and frame 0, both pixel-unshuffled; h the decoder's last
    activations (n, c0, H/s, W/s). With ``copy``, plus ``g * (pixels - y)``, the gate ``g`` (n, 7 s², H/s, W/s)
    a zero-initialised 1x1 convolution of the same hidden layer (the module docstring's copy term)."""

    def __init__(self, out_channels: int, channels: int, groups: int, hidden: int = 64, copy: bool = False):
        super().__init__()
        self.norm = torch.nn.GroupNorm(_groups(channels, groups), channels)
        self.conv_in = torch.nn.Conv2d(2 * out_channels + channels, hidden, 3, padding=1)
        self.conv_out = _zero(torch.nn.Conv2d(hidden, out_channels, 3, padding=1))
        self.copy = _zero(torch.nn.Conv2d(hidden, out_channels, 1)) if copy else None

    def forward(self, y: torch.Tensor, pixels: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        pixels = pixels.to(y.dtype)
        hidden = F.silu(self.conv_in(torch.cat([y, pixels, self.norm(h).to(y.dtype)], dim=1)))
        out = y + self.conv_out(hidden)
        if self.copy is not None:
            out = out + self.copy(hidden) * (pixels - y)
        return out


class FirstFrameAutoencoder(RGBDNAutoencoder):
    """The RGB-D-N autoencoder whose decoder also reads the clip's first frame (see the module docstring).

    Injection points (for ``block_out_channels`` (c0, ..., cL), ``n = L + 1`` blocks): after the mid
    block at the latent resolution (``cL`` channels), then after each up block; the reference at each
    point is frame 0's encoder feature at that resolution (``reference_channels``)."""

    def __init__(self, config: AutoencoderConfig):
        if config.first_frame_injection not in INJECTIONS:
            raise UserError(f"first_frame_injection must be one of {', '.join(INJECTIONS)}, "
                            f"got {config.first_frame_injection!r}")
        super().__init__(config)
        blocks = list(config.block_out_channels)
        n = len(blocks)
        # Decoder channels at each injection point: mid block, then each up block's output.
        rev = blocks[::-1]
        dec_channels = [rev[0]] + rev
        # Spatial level (0 = finest, the stem's resolution) of each injection point: up block i
        # upsamples except the last, so its output sits one level finer than its input.
        levels = [n - 1] + [max(n - 2 - i, 0) for i in range(n)]
        modules = []
        kind = config.first_frame_injection.split("+")[0]
        for ch, level in zip(dec_channels, levels):
            ref_ch = self.reference_channels(level)
            if kind == "attention" and level > 0:
                modules.append(AttentionInjection(ch, ref_ch, config.norm_num_groups))
            else:
                modules.append(ConcatInjection(ch, ref_ch, config.norm_num_groups))
        if config.first_frame_injection.endswith(OUTPUT_SPACE_SKIPS):
            out_ch = NUM_CHANNELS * config.stem ** 2
            modules.append(PixelSkip(out_ch, blocks[0], config.norm_num_groups,
                                     copy=config.first_frame_injection.endswith(COPY_SKIP)))
        self.first_frame = torch.nn.ModuleList(modules)
        self._levels = levels

    # ------------------------------------------------------------------ the reference
    def reference_channels(self, level: int) -> int:
        """Channels of frame 0's features at spatial level ``level`` (0 = the stem's resolution)."""
        blocks = self.config.block_out_channels
        if level == 0:
            return NUM_CHANNELS * self.config.stem ** 2 + blocks[0]
        if level == len(blocks) - 1:
            return 2 * blocks[-1]  # the last down block's output and the bottleneck's
        return blocks[level]

    @torch.no_grad()
    def reference_features(self, first_frame: torch.Tensor) -> list[torch.Tensor]:
        """First frames (n, 7, H, W) model space -> frame 0's features per spatial level, finest first:
        [(n, 7 s² + c0, H/s, W/s), (n, c1, H/2s, W/2s), ..., (n, 2 cL, H/f, W/f)], from the frozen encoder."""
        self._check(first_frame)
        enc = self.vae.encoder
        x = F.pixel_unshuffle(first_frame.to(self.device), self.config.stem)  # (n, 7 s², H/s, W/s)
        h = enc.conv_in(x)
        levels = []
        last = len(enc.down_blocks) - 1
        for i, block in enumerate(enc.down_blocks):
            for resnet in block.resnets:
                h = resnet(h, temb=None)
            if i == 0:
                levels.append(torch.cat([x.to(h.dtype), h], dim=1))
            elif i < last:
                levels.append(h)
            if block.downsamplers is not None:
                for down in block.downsamplers:
                    h = down(h)
        mid = enc.mid_block(h)
        if last == 0:
            levels[0] = torch.cat([levels[0], mid], dim=1)
        else:
            levels.append(torch.cat([h, mid], dim=1))
        return levels

    # ------------------------------------------------------------------ decoding
    def decode_raw_with_reference(self, z_raw: torch.Tensor, reference: list[torch.Tensor] | None) -> torch.Tensor:
        """Raw latents (n, C, h, w) and frame 0's features for each of the n frames (or None: the
        shipped decoder, no first-frame path) -> frames (n, 7, H, W), normals not yet unit."""
        vae = self.vae
        dec = vae.decoder
        h = vae.post_quant_conv(z_raw.contiguous()) if vae.post_quant_conv is not None else z_raw
        h = dec.conv_in(h)
        h = dec.mid_block(h, None)
        if reference is not None:
            h = self.first_frame[0](h, reference[self._levels[0]])
        for i, up in enumerate(dec.up_blocks):
            h = up(h, None)
            if reference is not None:
                h = self.first_frame[i + 1](h, reference[self._levels[i + 1]])
        y = dec.conv_out(dec.conv_act(dec.conv_norm_out(h)))
        if reference is not None and len(self.first_frame) > len(self._levels):
            pixels = reference[0][:, :y.shape[1]]  # frame 0 pixel-unshuffled (the finest level's first channels)
            y = self.first_frame[-1](y, pixels, h)
        return F.pixel_shuffle(y, self.config.stem)

    def decode_with_first_frame(self, z: torch.Tensor, first_frame: torch.Tensor | None) -> torch.Tensor:
        """Normalised latents (n, C, h, w) and each one's clip's first frame (n, 7, H, W) model space ->
        fp32 frames (n, 7, H, W) in [-1, 1], normals unit length. ``first_frame`` None: the shipped decoder."""
        reference = None if first_frame is None else self.reference_features(first_frame)
        x = self.decode_raw_with_reference(z.to(self.device) * self.latent_std + self.latent_mean, reference)
        return renormalize_normals(x.float().clamp(-1.0, 1.0))

    def decode(self, z: torch.Tensor, first_frame: torch.Tensor | None = None) -> torch.Tensor:
        """As :meth:`RGBDNAutoencoder.decode`, reading ``first_frame`` (n, 7, H, W) when given; without
        one, each latent's own plain decoding stands in for its first frame."""
        if first_frame is None:
            first_frame = self.decode_with_first_frame(z, None)
        return self.decode_with_first_frame(z, first_frame)

    def decode_clips(self, z: torch.Tensor, chunk: int = 16, first_frame: torch.Tensor | None = None) -> torch.Tensor:
        """Latents (b, t, C, h, w) and the clips' first frames (b, 7, H, W) model space -> clips
        (b, t, 7, H, W). ``first_frame`` None: frame 0 of each clip, decoded by the latent alone,
        stands in for it."""
        b, t = z.shape[:2]
        if first_frame is None:
            first_frame = self.decode_with_first_frame(z[:, 0], None)  # (b, 7, H, W)
        if first_frame.shape[0] != b:
            raise ValueError(f"{first_frame.shape[0]} first frames for {b} clips")
        reference = self.reference_features(first_frame)  # per clip, shared by its t frames
        out = []
        for i in range(b):
            zi = z[i]  # (t, C, h, w)
            for s in range(0, t, chunk):
                n = min(chunk, t - s)
                ref = [r[i:i + 1].expand(n, -1, -1, -1) for r in reference]
                x = self.decode_raw_with_reference(zi[s:s + n].to(self.device) * self.latent_std + self.latent_mean, ref)
                out.append(renormalize_normals(x.float().clamp(-1.0, 1.0)))
        return torch.cat(out).reshape(b, t, *out[0].shape[1:])


def from_autoencoder(base: RGBDNAutoencoder, injection: str) -> FirstFrameAutoencoder:
    """A first-frame autoencoder holding ``base``'s weights (encoder, decoder, latent statistics) with a
    fresh, zero-output first-frame path: it decodes exactly as ``base`` until trained. A ``base`` that is
    itself a first-frame autoencoder of this ``injection`` keeps its trained path (training goes on from it)."""
    import dataclasses

    name = base.config.name
    if base.config.first_frame_injection is None:
        name += f"-ff{injection[:3]}{'-px' if injection.endswith(PIXEL_SKIP) else '-cp' if injection.endswith(COPY_SKIP) else ''}"
    config = dataclasses.replace(base.config, first_frame_injection=injection, name=name)
    model = FirstFrameAutoencoder(config)
    missing, unexpected = model.load_state_dict(base.state_dict(), strict=False)
    if unexpected or any(not k.startswith(FIRST_FRAME_PREFIX) for k in missing):
        raise UserError(f"{base.config.name} does not fit a first-frame decoder of its own config "
                        f"(unexpected {unexpected[:3]}, missing {[k for k in missing if not k.startswith(FIRST_FRAME_PREFIX)][:3]})")
    return model
