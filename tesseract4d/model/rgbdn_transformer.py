"""The RGB-D-N video transformer: ``diffusers.CogVideoXTransformer3DModel`` with TesserAct's changes.

- Each modality (rgb, depth, normal) has its own input patch projection; its input is the noisy
  modality concatenated on channels with the same modality of the conditioning first frame
  (image-to-video conditioning). The projections' outputs are summed, so the token count does not
  grow. The RGB projection is the backbone's original one; depth and normal projections start at
  zero, so at initialisation depth/normal inputs do not change anything (the pretrained RGB model
  is intact).
- RGB leaves through the backbone's original output head, depth and normal through extra heads.
- Parameterisation: the network predicts the clean clip as "first frame + correction"
  (``x0_hat = condition[:, :1] + output``; a clip continuing from k history frames: each of them + its
  correction, the later frames on the last of them). Predicting the velocity directly failed in the pilot run
  (ENVIRONMENT.md); sampling turns ``x0_hat`` into a velocity (see pipeline.py).

Tensors are ``(b, t, c, h, w)``; ``c`` holds the modalities' channels in ``modality_channels``
order. Diffusion time ``t`` in [0, 1] (1 = pure noise) enters the backbone as ``1000 * t``.
"""

from __future__ import annotations

import torch
from torch import nn

from diffusers import CogVideoXTransformer3DModel
from diffusers.configuration_utils import ConfigMixin, register_to_config
from diffusers.models.embeddings import get_3d_rotary_pos_embed
from diffusers.models.modeling_utils import ModelMixin

from tesseract4d.model.model_space import MODALITIES

TIMESTEP_SCALE = 1000.0


def _ordered(modality_channels: dict[str, int]) -> list[str]:
    """Modalities in model-space order (config.json is saved with sorted keys, so dict order is lost)."""
    return [m for m in MODALITIES if m in modality_channels] + sorted(set(modality_channels) - set(MODALITIES))


class ModalityPatchProjection(nn.Module):
    """Sum of per-modality patch projections; stands in for the backbone's ``patch_embed.proj``.

    The backbone hands it either ``(n, C, h, w)`` (Conv2d path, ``patch_size_t`` None) or
    ``(b, tokens, C*p_t*p*p)`` with channels outermost (Linear path); ``C`` is the sum over
    modalities of ``2 * c_m`` (noisy + condition), in modality order.
    """

    def __init__(self, projections: dict[str, nn.Module], in_channels: dict[str, int], linear: bool):
        super().__init__()
        self.projs = nn.ModuleDict(projections)
        self.in_channels = dict(in_channels)
        self.linear = linear

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        sizes = [self.in_channels[name] for name in self.projs]
        if not self.linear:
            parts = torch.split(x, sizes, dim=1)  # each (n, 2*c_m, h, w)
            return sum(proj(part) for proj, part in zip(self.projs.values(), parts))
        b, n, f = x.shape
        total = sum(sizes)
        x = x.view(b, n, total, f // total)  # (b, tokens, C, p_t*p*p)
        parts = torch.split(x, sizes, dim=2)
        return sum(proj(part.reshape(b, n, -1)) for proj, part in zip(self.projs.values(), parts))


class ModalityOutputHeads(nn.Module):
    """Per-modality output heads; stands in for the backbone's ``proj_out``.

    Each head maps a token to ``c_m * [p_t *] p * p`` values laid out (c_m, [p_t,] p, p); the
    concatenation is what the backbone's unpatchify expects for ``sum(c_m)`` channels.
    """

    def __init__(self, heads: dict[str, nn.Module]):
        super().__init__()
        self.heads = nn.ModuleDict(heads)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.cat([head(h) for head in self.heads.values()], dim=-1)


class RGBDNTransformer(ModelMixin, ConfigMixin):
    """CogVideoX transformer over RGB-D-N clips (see the module docstring).

    Args:
        backbone_config: ``CogVideoXTransformer3DModel`` config (its ``in_channels``/``out_channels`` are
            set here from ``modality_channels``: the RGB projection takes ``2 * c_rgb``).
        modality_channels: channels per modality in the network's space, e.g.
            ``{"rgb": 3, "depth": 1, "normal": 3}`` in pixel space or 16 each in a VAE's latent space.
    """

    config_name = "config.json"
    _supports_gradient_checkpointing = True

    @register_to_config
    def __init__(self, backbone_config: dict, modality_channels: dict[str, int]):
        super().__init__()
        names = _ordered(modality_channels)
        # The first group uses the backbone's own projection and head: "rgb", or the single joint group
        # of an RGB-D-N autoencoder's latent (its channels mix the modalities).
        if not names or (names[0] != "rgb" and len(names) > 1):
            raise ValueError(f"modality_channels must start with 'rgb' (the backbone's own input) or be one joint "
                             f"group, got {names}")
        c_rgb = modality_channels[names[0]]
        cfg = dict(backbone_config)
        cfg.update(in_channels=2 * c_rgb, out_channels=c_rgb)
        self.backbone = CogVideoXTransformer3DModel(**cfg)
        bb = self.backbone
        linear = bb.config.patch_size_t is not None
        rgb_proj = bb.patch_embed.proj
        projs: dict[str, nn.Module] = {names[0]: rgb_proj}
        heads: dict[str, nn.Module] = {names[0]: bb.proj_out}
        patch_area = bb.config.patch_size**2 * (bb.config.patch_size_t or 1)
        inner = bb.proj_out.in_features
        for name in names[1:]:
            c = modality_channels[name]
            if linear:
                proj = nn.Linear(2 * c * patch_area, inner, bias=rgb_proj.bias is not None)
            else:
                proj = nn.Conv2d(2 * c, inner, kernel_size=rgb_proj.kernel_size, stride=rgb_proj.stride,
                                 bias=rgb_proj.bias is not None)
            nn.init.zeros_(proj.weight)
            if proj.bias is not None:
                nn.init.zeros_(proj.bias)
            projs[name] = proj
            heads[name] = nn.Linear(inner, c * patch_area)
        bb.patch_embed.proj = ModalityPatchProjection(projs, {n: 2 * modality_channels[n] for n in names}, linear)
        bb.proj_out = ModalityOutputHeads(heads)
        self._rotary_cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    # ------------------------------------------------------------------ helpers
    def channel_slices(self) -> dict[str, slice]:
        out, start = {}, 0
        for name in _ordered(self.config.modality_channels):
            c = self.config.modality_channels[name]
            out[name] = slice(start, start + c)
            start += c
        return out

    def zero_output_heads(self) -> None:
        """Zero every output head, so a fresh model predicts the first frame repeated (x0_hat = condition)."""
        with torch.no_grad():
            for head in self.backbone.proj_out.heads.values():
                head.weight.zero_()
                head.bias.zero_()

    def copy_rgb_head_to_other_heads(self) -> None:
        """Start depth/normal heads from the RGB head (TesserAct's init when fine-tuning a pretrained
        RGB model); only possible when the channel counts match (e.g. latent space)."""
        heads = self.backbone.proj_out.heads
        with torch.no_grad():
            for name, head in heads.items():
                if name != "rgb" and head.weight.shape == heads["rgb"].weight.shape:
                    head.load_state_dict(heads["rgb"].state_dict())

    def _rotary_embeddings(self, t: int, h: int, w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor] | None:
        cfg = self.backbone.config
        if not cfg.use_rotary_positional_embeddings:
            return None
        key = (t, h, w, str(device))
        if key not in self._rotary_cache:
            p, p_t = cfg.patch_size, cfg.patch_size_t
            grid = (h // p, w // p)
            if p_t is None:
                from diffusers.pipelines.cogvideo.pipeline_cogvideox import get_resize_crop_region_for_grid

                crops = get_resize_crop_region_for_grid(grid, cfg.sample_width // p, cfg.sample_height // p)
                emb = get_3d_rotary_pos_embed(cfg.attention_head_dim, crops, grid, t, device=device)
            else:
                emb = get_3d_rotary_pos_embed(cfg.attention_head_dim, None, grid, (t + p_t - 1) // p_t,
                                              grid_type="slice", max_size=(cfg.sample_height // p, cfg.sample_width // p),
                                              device=device)
            self._rotary_cache[key] = emb
        return self._rotary_cache[key]

    def enable_gradient_checkpointing(self) -> None:
        self.backbone.enable_gradient_checkpointing()

    # ------------------------------------------------------------------ forward
    def forward(self, sample: torch.Tensor, condition: torch.Tensor, encoder_hidden_states: torch.Tensor,
                t: torch.Tensor, history_frames: int = 1) -> torch.Tensor:
        """Predict the clean clip.

        sample: (b, t, c, h, w) noisy clip x_t = (1 - t) x0 + t noise.
        condition: (b, t, c, h, w) the first frame (repeated over time, or at frame 0 with zeros
            after it, as the preset says); zeros when dropped for guidance.
        encoder_hidden_states: (b, L, text_dim) text token embeddings (zeros when dropped).
        t: (b,) diffusion time in [0, 1].
        history_frames: k, how many given frames the condition's first latent frames hold (1: the first
            frame; k > 1: a clip continuing from the last k frames of the one before, codec.make_condition).
        Returns x0_hat (b, t, c, h, w) = given frame + correction: frame i < k on its own given frame, later
            frames on the last given one (k = 1: condition[:, :1] + correction).
        """
        b, nt, c, h, w = sample.shape
        slices = self.channel_slices()
        # (b, t, [x_rgb, cond_rgb, x_depth, cond_depth, x_normal, cond_normal], h, w)
        inp = torch.cat([torch.cat([sample[:, :, s], condition[:, :, s]], dim=2) for s in slices.values()], dim=2)
        rotary = self._rotary_embeddings(nt, h, w, sample.device)
        timestep = (t * TIMESTEP_SCALE).to(sample.dtype)
        out = self.backbone(inp, encoder_hidden_states, timestep, image_rotary_emb=rotary, return_dict=False)[0]
        if history_frames == 1:
            return condition[:, :1] + out  # (b, t, c, h, w)
        given = condition[:, :history_frames]  # (b, k, c, h, w)
        base = torch.cat([given, given[:, -1:].expand(-1, nt - history_frames, -1, -1, -1)], dim=1)
        return base + out  # (b, t, c, h, w)
