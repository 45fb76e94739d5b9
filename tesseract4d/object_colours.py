"""An object's own colours in a frame, and where a clip shows them (pure NumPy, no I/O).

The scene's objects are small cubes and cylinders of saturated colours on a wooden table, often
next to the white robot. An object's *distinctive* colours in a frame are the colours of its pixels
that lie farther than ``OBJECT_COLOUR_TOL`` (RGB distance, 0-255) from every colour shown just
around it (within a few pixels): a shaded cube keeps its lit top and its darker sides, while edge
pixels blended into the table are left out. A prediction then shows the object where pixels within
``OBJECT_COLOUR_TOL`` of those colours are. The held-out measures (object permanence, the
contrast's object finder) and the sampler's choice among noise draws all read colours this way.

Images are (H, W, 3) RGB, any numeric dtype; masks (H, W) bool.
"""

from __future__ import annotations

import numpy as np

# Colour distance (RGB, 0-255) within which a pixel counts as one of an object's colours.
OBJECT_COLOUR_TOL = 40.0
# An object with fewer pixels than this in a frame is too small to read its colours there.
MIN_OBJECT_PIXELS = 4


def dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` grown by ``px`` pixels (4-neighbourhood steps) in its last two axes."""
    out = np.asarray(mask, bool).copy()
    for _ in range(px):
        grown = out.copy()
        grown[..., 1:, :] |= out[..., :-1, :]
        grown[..., :-1, :] |= out[..., 1:, :]
        grown[..., :, 1:] |= out[..., :, :-1]
        grown[..., :, :-1] |= out[..., :, 1:]
        out = grown
    return out


def min_colour_distance(colours: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """For each of ``colours`` (N, 3), the RGB distance to the nearest of ``palette`` (M, 3)."""
    colours, palette = np.asarray(colours, np.float64), np.asarray(palette, np.float64)
    if len(palette) == 0:
        return np.full(len(colours), np.inf, np.float32)
    # |c - p|^2 = |c|^2 - 2 c.p + |p|^2 as one matrix product: exact for 0-255 integer colours (float64
    # holds every term), and five to ten times faster than the (N, M, 3) differences on the object layer's sizes
    out = np.empty(len(colours), np.float64)
    p_sq = (palette**2).sum(axis=1)
    step = max(1, _PAIRS_PER_CHUNK // len(palette))
    for i in range(0, len(colours), step):
        c = colours[i:i + step]
        d_sq = (c**2).sum(axis=1)[:, None] - 2.0 * (c @ palette.T) + p_sq[None, :]
        out[i:i + step] = d_sq.min(axis=1)
    return np.sqrt(np.maximum(out, 0.0)).astype(np.float32)


_PAIRS_PER_CHUNK = 1 << 21  # colour-palette pairs per matrix product (16 MiB of float64)


def distinctive(rgb: np.ndarray, mask: np.ndarray, around_px: int) -> np.ndarray:
    """(mask.sum(),) bool: which of the object's pixels (``rgb[mask]``, row-major) have a colour
    farther than ``OBJECT_COLOUR_TOL`` from every pixel within ``around_px`` outside the mask."""
    rgb = np.asarray(rgb, np.float32)
    mask = np.asarray(mask, bool)
    around = rgb[dilate(mask, around_px) & ~mask]
    return min_colour_distance(rgb[mask], around) > OBJECT_COLOUR_TOL


def matches(rgb: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of ``rgb`` (H, W, 3) within ``OBJECT_COLOUR_TOL`` of a colour of ``palette``."""
    rgb = np.asarray(rgb, np.float32)
    return min_colour_distance(rgb.reshape(-1, 3), palette).reshape(rgb.shape[:2]) < OBJECT_COLOUR_TOL
