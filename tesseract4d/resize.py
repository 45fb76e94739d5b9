"""Resizing an RGB-D-N frame or clip, with its intrinsics K, by a whole factor (pure numpy, no I/O).

Where a model and data disagree on resolution (held-out evaluation of checkpoints of several
resolutions on one data set) the first frame goes to the model's resolution and the prediction
comes back with :func:`resize_rgbdn`. The factor is a whole number k or 1/k, the same on both
axes (:func:`resize_factor`), so every output pixel covers exactly k×k input pixels or 1/k of one.

Per modality:

- RGB: shrinking averages each k×k block (area interpolation); enlarging is bilinear. Both take
  pixel centres at half-integers and replicate edge pixels, as OpenCV's INTER_AREA / INTER_LINEAR.
- ``depth_m`` and ``normal_cam`` are never averaged across a depth edge or a crease, so no point
  floats between a foreground object and the background behind it:

  - shrinking: each block takes one of its own samples, of its valid ones (depth > 0) the one of
    lower-median depth (the surface that covers most of the block; a tie goes to the nearer
    surface), with that sample's normal; a block with fewer than half its pixels valid is
    invalid (0);
  - enlarging: inside a surface (the four input neighbours valid, their depths within
    ``DEPTH_EDGE_REL`` of each other and their normals within ``NORMAL_CREASE_DEG``) inverse depth
    and normals are interpolated bilinearly (inverse depth is affine in pixel coordinates across
    a plane, so a plane stays that plane); anywhere else the nearest input pixel is copied.

  Normals come out unit length, or zero where there is no measurement; invalid depth (0,
  negative or non-finite) comes out as 0.
- K: pixel centres lie at half-integers (``geometry.pixel_grid``), so pixel coordinates scale by
  the factor s with no offset: fx, fy, cx, cy (and the skew) are multiplied by s.

Shapes: ``rgb`` (..., H, W, 3), ``depth_m`` (..., H, W), ``normal_cam`` (..., H, W, 3), ``K``
(..., 3, 3): one frame, or a clip with leading (T,).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from tesseract4d.errors import UserError
from tesseract4d.geometry import MIN_NORMAL_LENGTH
from tesseract4d.dataset_format import CameraFrames

# Enlarging interpolates depth only between neighbours whose depths differ by at most this share
# (2 cm at 1 m); a step beyond it is an edge and the nearest pixel is copied instead. A plane seen
# very obliquely can exceed it across one input pixel too; copying is the safe side of that mistake.
DEPTH_EDGE_REL = 0.02
# ... and whose normals differ by at most this angle (a crease, e.g. a box's edge, is not blended).
NORMAL_CREASE_DEG = 20.0


def resize_factor(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> Fraction | None:
    """The scale s = dst / src when it is a whole number k or 1/k, the same on both axes; else None."""
    (h, w), (H, W) = (int(x) for x in src_hw), (int(x) for x in dst_hw)
    if min(h, w, H, W) < 1:
        return None
    s = Fraction(H, h)
    if Fraction(W, w) != s or (s.numerator != 1 and s.denominator != 1):
        return None
    return s


def scale_intrinsics(K: np.ndarray, s: float | Fraction) -> np.ndarray:
    """K (..., 3, 3) of the same camera in an image scaled by s (pixel centres at half-integers), float64."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[..., :2, :] *= float(s)
    return out


def resize_rgbdn(rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray, K: np.ndarray,
                 height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An RGB-D-N frame or clip and its K at ``height`` x ``width`` (see the module docstring).

    Returns (rgb, depth_m, normal_cam, K) in the input dtypes (K float64); the same size returns
    copies of the inputs. Raises UserError when the size is not a whole factor up or down.
    """
    rgb, depth, normal = np.asarray(rgb), np.asarray(depth_m), np.asarray(normal_cam)
    src = depth.shape[-2:]
    if rgb.shape[:-1] != depth.shape or normal.shape != rgb.shape:
        raise ValueError(f"rgb {rgb.shape}, depth_m {depth.shape} and normal_cam {normal.shape} do not match")
    s = resize_factor(src, (height, width))
    if s is None:
        raise UserError(f"cannot resize {src[0]}x{src[1]} frames to {height}x{width}: only by a whole factor, the same "
                        f"on both axes; use data whose resolution is a whole multiple or divisor of the model's")
    if s == 1:
        return rgb.copy(), depth.copy(), normal.copy(), np.array(K, dtype=np.float64)
    if s < 1:
        k = s.denominator
        rgb_out = _shrink_rgb(rgb, k)
        depth_out, normal_out = _shrink_geometry(depth, normal, k)
    else:
        k = s.numerator
        rgb_out = _enlarge_rgb(rgb, k)
        depth_out, normal_out = _enlarge_geometry(depth, normal, k)
    return (rgb_out.astype(rgb.dtype), depth_out.astype(depth.dtype), normal_out.astype(normal.dtype),
            scale_intrinsics(K, s))


def episode_at_resolution(episode, camera: str, hw: tuple[int, int]):
    """A dataset Episode with only ``camera``, its RGB-D-N and K resized to ``hw`` by :func:`resize_rgbdn`
    (itself when already there). The resized copy carries no segmentation (so a sampler with several
    noise draws chooses among them by the objects found by their colour: draw_choice.py)."""
    import dataclasses

    cam = episode.cameras[camera]
    if tuple(cam.rgb.shape[1:3]) == tuple(hw) and list(episode.cameras) == [camera]:
        return episode
    rgb, depth_m, normal_cam, K = resize_rgbdn(cam.rgb, cam.depth_m, cam.normal_cam, cam.K, *hw)
    frames = CameraFrames(rgb=rgb, depth_m=depth_m, normal_cam=normal_cam, K=K, T_world_cam=cam.T_world_cam)
    return dataclasses.replace(episode, cameras={camera: frames})


def _valid_depth(depth: np.ndarray) -> np.ndarray:
    return np.isfinite(depth) & (depth > 0)


def _unit(n: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3); those shorter than MIN_NORMAL_LENGTH (no measurement) become 0."""
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(length > MIN_NORMAL_LENGTH, n / np.maximum(length, 1e-12), 0.0)


def _to_dtype_range(x: np.ndarray, dtype) -> np.ndarray:
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return np.clip(np.rint(x), info.min, info.max)
    return x


def _blocks(a: np.ndarray, k: int, channels: bool) -> np.ndarray:
    """(..., H, W[, c]) -> (..., H/k, W/k, k*k[, c]): the k×k block of every output pixel."""
    lead = a.shape[:-3] if channels else a.shape[:-2]
    H, W = (a.shape[-3:-1] if channels else a.shape[-2:])
    tail = a.shape[-1:] if channels else ()
    b = a.reshape(*lead, H // k, k, W // k, k, *tail)  # (..., h, k, w, k[, c])
    b = np.moveaxis(b, len(lead) + 2, len(lead) + 1)  # (..., h, w, k, k[, c])
    return b.reshape(*lead, H // k, W // k, k * k, *tail)


def _shrink_rgb(rgb: np.ndarray, k: int) -> np.ndarray:
    return _to_dtype_range(_blocks(rgb.astype(np.float64), k, channels=True).mean(-2), rgb.dtype)


def _shrink_geometry(depth: np.ndarray, normal: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    d = _blocks(depth.astype(np.float64), k, channels=False)  # (..., h, w, k*k)
    n = _blocks(normal.astype(np.float64), k, channels=True)  # (..., h, w, k*k, 3)
    valid = _valid_depth(d)
    count = valid.sum(-1)
    order = np.argsort(np.where(valid, d, np.inf), axis=-1, kind="stable")  # valid samples first, nearest first
    rank = np.maximum(count - 1, 0) // 2  # the lower median of the valid samples
    pick = np.take_along_axis(order, rank[..., None], axis=-1)  # (..., h, w, 1)
    keep = 2 * count >= k * k
    depth_out = np.where(keep, np.take_along_axis(d, pick, axis=-1)[..., 0], 0.0)
    normal_out = np.take_along_axis(n, pick[..., None], axis=-2)[..., 0, :]
    return depth_out, np.where(keep[..., None], _unit(normal_out), 0.0)


def _taps(n: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps of enlarging n pixels k times along one axis: (i0, i1, weight of i1, nearest)."""
    x = (np.arange(n * k) + 0.5) / k - 0.5  # output pixel centres in input index units
    x0 = np.floor(x)
    return (np.clip(x0, 0, n - 1).astype(int), np.clip(x0 + 1, 0, n - 1).astype(int), x - x0,
            np.arange(n * k) // k)


def _gather(a: np.ndarray, ys: np.ndarray, xs: np.ndarray, channels: bool) -> np.ndarray:
    return a[..., ys, :, :][..., xs, :] if channels else a[..., ys, :][..., xs]


def _enlarge_rgb(rgb: np.ndarray, k: int) -> np.ndarray:
    y0, y1, wy, _ = _taps(rgb.shape[-3], k)
    x0, x1, wx, _ = _taps(rgb.shape[-2], k)
    a = rgb.astype(np.float64)
    wy, wx = wy[:, None, None], wx[None, :, None]
    out = ((1 - wy) * ((1 - wx) * _gather(a, y0, x0, True) + wx * _gather(a, y0, x1, True))
           + wy * ((1 - wx) * _gather(a, y1, x0, True) + wx * _gather(a, y1, x1, True)))
    return _to_dtype_range(out, rgb.dtype)


def _enlarge_geometry(depth: np.ndarray, normal: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    y0, y1, wy, ny = _taps(depth.shape[-2], k)
    x0, x1, wx, nx = _taps(depth.shape[-1], k)
    d = np.where(_valid_depth(depth), depth.astype(np.float64), 0.0)
    n = _unit(normal.astype(np.float64))
    corners = ((y0, x0), (y0, x1), (y1, x0), (y1, x1))
    weights = [(1 - wy)[:, None] * (1 - wx)[None, :], (1 - wy)[:, None] * wx[None, :],
               wy[:, None] * (1 - wx)[None, :], wy[:, None] * wx[None, :]]  # each (H*k, W*k)
    ds = np.stack([_gather(d, ys, xs, False) for ys, xs in corners])  # (4, ..., H*k, W*k)
    ns = np.stack([_gather(n, ys, xs, True) for ys, xs in corners])  # (4, ..., H*k, W*k, 3)
    # Inside a surface: all four valid, no depth step, no crease.
    dmin, dmax = ds.min(0), ds.max(0)
    smooth = (dmin > 0) & (dmax <= dmin * (1 + DEPTH_EDGE_REL))
    smooth &= (np.linalg.norm(ns, axis=-1) > MIN_NORMAL_LENGTH).all(0)
    min_cos = np.min([(ns[i] * ns[j]).sum(-1) for i in range(4) for j in range(i + 1, 4)], axis=0)
    smooth &= min_cos >= np.cos(np.deg2rad(NORMAL_CREASE_DEG))
    with np.errstate(divide="ignore"):
        inv = sum(w / np.where(ds[i] > 0, ds[i], np.inf) for i, w in enumerate(weights))
        interp_depth = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), 0.0)
    interp_normal = _unit(sum(w[..., None] * ns[i] for i, w in enumerate(weights)))
    depth_out = np.where(smooth, interp_depth, _gather(d, ny, nx, False))
    normal_out = np.where(smooth[..., None], interp_normal, _gather(n, ny, nx, True))
    return depth_out, normal_out
