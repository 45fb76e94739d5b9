"""Model space: how each modality maps to network inputs and back. Shared by training and sampling.

One clip in model space is a float tensor ``(t, c, h, w)`` (or batched ``(b, t, c, h, w)``) with the
channels of the modalities stacked in ``MODALITIES`` order (rgb 3, depth 1, normal 3 = 7), all
roughly in [-1, 1]:

- rgb: uint8 [0, 255] -> [-1, 1] linearly.
- depth: metric z-depth in a fixed range ``[near_m, far_m]`` -> [-1, 1] linearly, so predicted depth
  is metric. Depth outside the range is clipped; "no hit" (0) and anything beyond ``far_m`` encode
  as +1 (far). On the way back, depths within ``FAR_BAND`` of ``far_m`` decode to 0 ("beyond the
  range / no measurement" in the dataset format).
- normal: unit vectors in the OpenCV camera frame, already in [-1, 1] per axis, kept as they are
  ("no hit" stays 0). On the way back they are renormalised to unit length; vectors shorter than
  ``MIN_NORMAL_LENGTH`` decode to 0 (no hit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

MODALITIES: tuple[str, ...] = ("rgb", "depth", "normal")
MODALITY_CHANNELS: dict[str, int] = {"rgb": 3, "depth": 1, "normal": 3}
NUM_CHANNELS = sum(MODALITY_CHANNELS.values())
FAR_BAND = 0.01  # share of the depth range below far_m that decodes as "beyond the range"
MIN_NORMAL_LENGTH = 0.3

# The close camera (datagen/cameras.py) sees the table and objects at 0.3-1.2 m; the floor
# behind the table is farther and saturates at far_m.
DEFAULT_NEAR_M = 0.2
DEFAULT_FAR_M = 1.5


def channel_slices() -> dict[str, slice]:
    """Channel range of each modality in a model-space tensor."""
    out, start = {}, 0
    for name in MODALITIES:
        out[name] = slice(start, start + MODALITY_CHANNELS[name])
        start += MODALITY_CHANNELS[name]
    return out


@dataclass(frozen=True)
class ModelSpace:
    """The fixed mapping between dataset arrays and network values; saved with every checkpoint."""

    near_m: float = DEFAULT_NEAR_M
    far_m: float = DEFAULT_FAR_M

    def to_dict(self) -> dict:
        return {"near_m": self.near_m, "far_m": self.far_m}

    # ------------------------------------------------------------------ encode
    def encode(self, rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray) -> torch.Tensor:
        """Dataset arrays of T frames -> model space (T, 7, H, W) float32.

        rgb (T, H, W, 3) uint8; depth_m (T, H, W) metres, 0 = no hit; normal_cam (T, H, W, 3) unit.
        """
        rgb_t = torch.from_numpy(np.ascontiguousarray(rgb)).float().div(127.5).sub(1.0)  # (t, h, w, 3)
        depth = np.asarray(depth_m, np.float32)
        depth = np.where(depth > 0, depth, self.far_m)
        depth_t = torch.from_numpy(depth).clamp(self.near_m, self.far_m)
        depth_t = (depth_t - self.near_m) / (self.far_m - self.near_m) * 2.0 - 1.0  # (t, h, w)
        normal_t = torch.from_numpy(np.asarray(normal_cam, np.float32)).clamp(-1.0, 1.0)  # (t, h, w, 3)
        x = torch.cat([rgb_t, depth_t[..., None], normal_t], dim=-1)  # (t, h, w, 7)
        return x.permute(0, 3, 1, 2).contiguous()  # (t, 7, h, w)

    # ------------------------------------------------------------------ decode
    def decode(self, x: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Model space (T, 7, H, W) -> (rgb uint8 (T, H, W, 3), depth_m (T, H, W), normal_cam (T, H, W, 3))."""
        x = x.detach().float().cpu().clamp(-1.0, 1.0)
        s = channel_slices()
        rgb = ((x[:, s["rgb"]] + 1.0) * 127.5).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
        unit = (x[:, s["depth"]][:, 0] + 1.0) / 2.0  # (t, h, w) in [0, 1]
        depth_m = self.near_m + unit * (self.far_m - self.near_m)
        depth_m = torch.where(unit >= 1.0 - FAR_BAND, torch.zeros_like(depth_m), depth_m).numpy().astype(np.float32)
        n = x[:, s["normal"]]  # (t, 3, h, w)
        length = n.square().sum(dim=1, keepdim=True).sqrt()  # over channels before the permute (renormalize_normals)
        normal = torch.where(length >= MIN_NORMAL_LENGTH, n / length.clamp_min(1e-6), torch.zeros_like(n))
        return rgb, depth_m, normal.permute(0, 2, 3, 1).numpy().astype(np.float32)



def renormalize_normals(x: torch.Tensor) -> torch.Tensor:
    """Model-space frames (..., 7, H, W) with the normal channels scaled to unit length; vectors
    shorter than ``MIN_NORMAL_LENGTH`` become 0 (no hit). Differentiable where the length is kept."""
    s = channel_slices()["normal"]
    n = x[..., s, :, :]  # (..., 3, h, w)
    # Not n.norm(dim=-3): a norm across the channel stride is about 100x slower on a CPU (a fifth
    # of a 16-frame decode); the clamp before the root keeps the gradient finite at zero length.
    length = n.square().sum(dim=-3, keepdim=True).clamp_min(1e-12).sqrt()
    unit = torch.where(length >= MIN_NORMAL_LENGTH, n / length, torch.zeros_like(n))
    return torch.cat([x[..., :s.start, :, :], unit, x[..., s.stop:, :, :]], dim=-3)
