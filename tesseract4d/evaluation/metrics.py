"""Metrics of predicted / reconstructed RGB-D-N against ground truth: pure functions on arrays.

Definitions (what the report's numbers mean):

* ``chamfer_l1_m``: symmetric Chamfer distance with unsquared Euclidean nearest-neighbour
  distances, in metres: ``0.5 * (mean_a min_b |a - b| + mean_b min_a |b - a|)``.
* ``depth_metrics``: AbsRel ``mean |pred - gt| / gt``; δ1 / δ2 the share of pixels with
  ``max(pred / gt, gt / pred)`` below 1.25 / 1.25²; valid pixels only (gt > 0 and pred > 0, finite).
* ``normal_metrics``: angle between unit normals in degrees (mean, median) and the share of
  pixels under 11.25°; pixels where both normals exist.
* ``rgb_psnr``: defined in :mod:`tesseract4d.psnr` (shared with training validation).
* ``rgb_ssim``: SSIM of Wang et al. 2004 (11x11 Gaussian window, σ = 1.5, K1 = 0.01,
  K2 = 0.03) on each colour channel, averaged.

Shares are fractions in [0, 1]. An empty selection gives NaN.
"""

from __future__ import annotations

import numpy as np

from tesseract4d.geometry import MIN_NORMAL_LENGTH
from tesseract4d.motion import MOVING_DEPTH_TOL_M, MOVING_DEPTH_TOL_REL, MOVING_RGB_TOL, depth_tolerance_m
from tesseract4d.psnr import PSNR_MAX_DB, peak_value, pixel_mask, rgb_psnr

__all__ = ["PSNR_MAX_DB", "rgb_psnr", "chamfer_l1_m", "depth_metrics", "normal_metrics", "rgb_ssim", "ssim_map",
           "moving_region_mask"]

DELTA = 1.25
NORMAL_GOOD_DEG = 11.25
# A ground truth in which fewer pixels than this change per frame on average is still: what changes is a
# pixel or two of render noise (a frame-0 speck at an edge), not motion, and its moving region is empty.
# (Measured over one flickering pixel, a moving-region metric says nothing about the motion.)
MIN_MOVING_PIXELS_PER_FRAME = 4


def chamfer_l1_m(points_a: np.ndarray, points_b: np.ndarray) -> float:
    """Symmetric Chamfer distance (metres) between (N, 3) and (M, 3) point sets; NaN if either
    is empty. See the module docstring for the definition."""
    from scipy.spatial import cKDTree

    a = np.asarray(points_a, np.float64).reshape(-1, 3)
    b = np.asarray(points_b, np.float64).reshape(-1, 3)
    a, b = a[np.all(np.isfinite(a), -1)], b[np.all(np.isfinite(b), -1)]
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    d_ab = cKDTree(b).query(a, k=1)[0]
    d_ba = cKDTree(a).query(b, k=1)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def depth_metrics(pred_m: np.ndarray, gt_m: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """abs_rel, delta1, delta2 over pixels valid in both maps (and in ``mask``). Any shape."""
    pred, gt = np.asarray(pred_m, np.float64), np.asarray(gt_m, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"depth shapes differ: pred {pred.shape}, gt {gt.shape}")
    ok = pixel_mask(mask, gt.shape) & np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if not ok.any():
        return {"abs_rel": float("nan"), "delta1": float("nan"), "delta2": float("nan")}
    p, g = pred[ok], gt[ok]
    ratio = np.maximum(p / g, g / p)
    return {
        "abs_rel": float(np.mean(np.abs(p - g) / g)),
        "delta1": float(np.mean(ratio < DELTA)),
        "delta2": float(np.mean(ratio < DELTA**2)),
    }


def normal_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """mean_deg, median_deg, within_11_25 over pixels where both normals exist (longer than
    ``geometry.MIN_NORMAL_LENGTH``).
    pred, gt: (..., 3)."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"normal shapes must match and end in 3: pred {pred.shape}, gt {gt.shape}")
    len_p, len_g = np.linalg.norm(pred, axis=-1), np.linalg.norm(gt, axis=-1)
    ok = pixel_mask(mask, gt.shape[:-1]) & np.isfinite(len_p) & np.isfinite(len_g) & (len_p > MIN_NORMAL_LENGTH) & (len_g > MIN_NORMAL_LENGTH)
    if not ok.any():
        return {"mean_deg": float("nan"), "median_deg": float("nan"), "within_11_25": float("nan")}
    cos = np.sum(pred[ok] * gt[ok], -1) / (len_p[ok] * len_g[ok])
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return {
        "mean_deg": float(angle.mean()),
        "median_deg": float(np.median(angle)),
        "within_11_25": float(np.mean(angle < NORMAL_GOOD_DEG)),
    }


def ssim_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (H, W) of two (H, W, C) or (H, W) images, averaged over channels."""
    import cv2

    peak = peak_value(gt)
    p = np.asarray(pred, np.float64) / peak
    g = np.asarray(gt, np.float64) / peak
    if p.shape != g.shape:
        raise ValueError(f"image shapes differ: pred {p.shape}, gt {g.shape}")
    if p.ndim == 2:
        p, g = p[..., None], g[..., None]
    c1, c2 = 0.01**2, 0.03**2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    out = np.zeros(p.shape[:2])
    for c in range(p.shape[-1]):
        x, y = np.ascontiguousarray(p[..., c]), np.ascontiguousarray(g[..., c])
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        out += ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return out / p.shape[-1]


def rgb_ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM of two (H, W, C) images, over ``mask`` (H, W) if given."""
    m = ssim_map(pred, gt)
    ok = pixel_mask(mask, m.shape)
    return float(m[ok].mean()) if ok.any() else float("nan")


def moving_region_mask(frames, rgb_tol: float = MOVING_RGB_TOL, depth_tol_m: float = MOVING_DEPTH_TOL_M,
                       depth_tol_rel: float = MOVING_DEPTH_TOL_REL) -> np.ndarray:
    """Pixels whose ground truth changes over the clip, (T, H, W) bool.

    ``frames``: a CameraFrames (or anything with ``rgb`` (T, H, W, 3) and ``depth_m`` (T, H, W)).
    Frame t > 0: pixels whose RGB (any channel) or depth differs from frame 0 beyond the
    tolerances (:mod:`tesseract4d.motion`). Frame 0 has nothing to differ from; it gets the pixels that change in any later
    frame (what is about to move, or be uncovered). Fewer than ``MIN_MOVING_PIXELS_PER_FRAME`` changing
    pixels per frame on average: a still clip, no moving region.
    """
    rgb = np.asarray(frames.rgb, np.int16)
    depth = np.asarray(frames.depth_m, np.float64)
    depth = np.where(np.isfinite(depth), depth, 0.0)
    rgb_change = np.abs(rgb - rgb[:1]).max(-1) > rgb_tol
    depth_change = np.abs(depth - depth[:1]) > depth_tolerance_m(np.maximum(depth, depth[:1]), depth_tol_m, depth_tol_rel)
    moving = rgb_change | depth_change
    moving[0] = moving[1:].any(0) if len(moving) > 1 else False
    if moving.sum() < MIN_MOVING_PIXELS_PER_FRAME * len(moving):
        moving[:] = False
    return moving
