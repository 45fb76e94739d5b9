"""Keep the given first frame where a predicted clip does not change.

A latent model redraws every pixel of every frame through its decoder, so even the parts of the
scene it predicts to stay put come out as the autoencoder draws them: a softer table grain, rounder
cube corners, slightly off depth and normals. The first frame itself is known exactly. Where the
prediction does not change over time, the composite puts the first frame's own pixels back:

    out_t = (1 - m_t) pred_t + m_t first

``m_t`` in [0, 1] says how still pixel (t, y, x) is predicted to be: 1 where the largest change of
``pred_t`` from ``pred_0`` (the model's own drawing of the first frame) over the channels, taken over a
small neighbourhood (``STATIC_MARGIN_PX``, so that the blurred rim of something moving is not counted as
still), stays below half the tolerance, 0 above the tolerance, linear between. A pixel the model moves
is left exactly as predicted; a still one becomes exactly the first frame's; frame 0 becomes the first
frame. The composite takes nothing from the future: it decides from the prediction and the first frame.
"""

from __future__ import annotations

import torch

# Pixels within this many pixels of a predicted change count as changing too.
STATIC_MARGIN_PX = 2


def dilate_max(x: torch.Tensor, radius_px: int) -> torch.Tensor:
    """The maximum of ``x`` (..., H, W) over the (2r + 1)² window around each pixel, as
    ``max_pool2d(x, 2r + 1, stride=1, padding=r)``, in shifted maxima along each axis (a tenth of
    max_pool2d's time on a CPU for a 16-frame 128² clip)."""
    for dim in (-2, -1):
        out, n = x.clone(), x.shape[dim]
        for d in range(1, min(radius_px, n - 1) + 1):
            ahead, behind = out.narrow(dim, d, n - d), out.narrow(dim, 0, n - d)
            torch.maximum(ahead, x.narrow(dim, 0, n - d), out=ahead)
            torch.maximum(behind, x.narrow(dim, d, n - d), out=behind)
        x = out
    return x


def stillness(clip: torch.Tensor, tolerance: float, margin_px: int = STATIC_MARGIN_PX) -> torch.Tensor:
    """(b, T, H, W) in [0, 1]: 1 where ``clip`` (b, T, C, H, W) stays within ``tolerance / 2`` of its
    frame 0 in every channel (and so does every pixel within ``margin_px``), 0 where it moves by more
    than ``tolerance``, linear between."""
    if tolerance <= 0:
        raise ValueError(f"tolerance must be > 0, got {tolerance}")
    change = (clip - clip[:, :1]).abs().amax(dim=2)  # (b, T, H, W)
    return ((tolerance - dilate_max(change, margin_px)) / (tolerance / 2)).clamp(0.0, 1.0)


def composite_static(clip: torch.Tensor, first_frame: torch.Tensor, tolerance: float,
                     margin_px: int = STATIC_MARGIN_PX) -> torch.Tensor:
    """``clip`` (b, T, C, H, W) with ``first_frame`` (b, C, H, W) put back where it is still (see the
    module); both in model space, the result clamped to [-1, 1] as decoded clips are."""
    if first_frame.shape != clip[:, 0].shape:
        raise ValueError(f"first_frame must be {tuple(clip[:, 0].shape)}, got {tuple(first_frame.shape)}")
    m = stillness(clip, tolerance, margin_px)[:, :, None]
    return torch.lerp(clip, first_frame.to(clip)[:, None], m).clamp(-1.0, 1.0)
