"""PSNR, the one definition used by training validation, evaluation reports and the viewer.

``rgb_psnr``: 10 log10(peak² / MSE) in dB (peak 255 for integer images, 1 for float images),
at most ``PSNR_MAX_DB`` (identical images, e.g. a prediction's conditioning frame, would give
infinity and make every average infinite). Pure numpy; torch tensors on the CPU are accepted.
"""

from __future__ import annotations

import numpy as np

PSNR_MAX_DB = 100.0


def peak_value(img) -> float:
    """The largest value an image can hold: 255 for integer images, 1 for float images."""
    return 255.0 if np.issubdtype(np.asarray(img).dtype, np.integer) else 1.0


def pixel_mask(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """``mask`` as a bool array of ``shape`` (all pixels when None); ValueError if it does not fit."""
    if mask is None:
        return np.ones(shape, bool)
    mask = np.asarray(mask, bool)
    if mask.shape != shape:
        raise ValueError(f"mask shape {mask.shape} does not match the images' {shape}")
    return mask


def rgb_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images (..., H, W, C); ``mask`` (..., H, W) selects pixels. Without a mask
    the layout does not matter (any shape, e.g. (T, C, H, W) tensors). NaN for an empty mask."""
    p, g = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if p.shape != g.shape:
        raise ValueError(f"image shapes differ: pred {p.shape}, gt {g.shape}")
    ok = pixel_mask(mask, g.shape[:-1])
    if not ok.any():
        return float("nan")
    peak = peak_value(gt)
    mse = float(np.mean((p[ok] - g[ok]) ** 2))
    floor = peak**2 * 10 ** (-PSNR_MAX_DB / 10)
    return float(10.0 * np.log10(peak**2 / max(mse, floor)))
