"""The colour maps of depth and normals, for MP4 previews and the viewer alike (no I/O).

Every function returns uint8 RGB. Depth uses the "turbo" colormap (OpenCV's table) over a
fixed range per clip or source (so colours mean the same depth in every frame): near is blue,
far is red; the range is the valid depths' ``DEPTH_PERCENTILES``. Normals map [-1, 1] to [0, 255].
"""

from __future__ import annotations

import functools

import numpy as np

# GUI label -> mode key. The order is the dropdown order.
COLOR_MODES: dict[str, str] = {
    "RGB": "rgb",
    "Normal": "normal",
    "Depth": "depth",
    "Static / dynamic": "dynamic",
}
STATIC_RGB = np.array([90, 140, 200], np.uint8)
DYNAMIC_RGB = np.array([245, 130, 30], np.uint8)
INVALID_RGB = np.array([0, 0, 0], np.uint8)

# The depth range: these percentiles of the valid depths. The far end is well below the
# maximum because a far background would otherwise take most of the colour range.
DEPTH_PERCENTILES = (2.0, 90.0)
TURBO_LEVELS = 256


@functools.lru_cache(maxsize=1)
def _turbo_table() -> np.ndarray:
    """(TURBO_LEVELS, 3) uint8 RGB: OpenCV's TURBO colormap, level 0 (blue) to 255 (red)."""
    import cv2

    levels = np.arange(TURBO_LEVELS, dtype=np.uint8)[:, None]  # (256, 1) one-channel image
    return np.ascontiguousarray(cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[:, 0, ::-1])  # BGR -> RGB


def turbo(x: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] (any shape) to uint8 RGB (shape + (3,)); values are clipped, NaN is 0."""
    x = np.clip(np.nan_to_num(np.asarray(x, np.float32)), 0.0, 1.0)
    return _turbo_table()[((TURBO_LEVELS - 1) * x).astype(np.int32)]


def depth_range(depths: np.ndarray) -> tuple[float, float]:
    """Robust (near, far) in metres from valid (> 0, finite) depth samples of any shape."""
    d = np.asarray(depths, np.float32)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        return 0.0, 1.0
    near, far = np.percentile(d, DEPTH_PERCENTILES)
    if far - near < 1e-6:
        far = near + 1e-3
    return float(near), float(far)


def colorize_depth(depth_m: np.ndarray, near: float, far: float) -> np.ndarray:
    """Depth (…) in metres to turbo RGB (…, 3); 0 / non-finite depth is black."""
    d = np.asarray(depth_m, np.float32)
    rgb = turbo((d - near) / max(far - near, 1e-6))
    rgb[~(np.isfinite(d) & (d > 0))] = INVALID_RGB
    return rgb


def colorize_normals(normals: np.ndarray) -> np.ndarray:
    """Unit normals (…, 3) to RGB (…, 3) via (n + 1) / 2; zero vectors (no data) are black."""
    n = np.asarray(normals, np.float32)
    rgb = ((np.clip(n, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    rgb[np.all(n == 0, axis=-1)] = INVALID_RGB
    return rgb


def colorize_dynamic(dynamic: np.ndarray) -> np.ndarray:
    """Boolean mask (N,) to RGB (N, 3): static points blue, moving points orange."""
    return np.where(np.asarray(dynamic, bool)[:, None], DYNAMIC_RGB, STATIC_RGB).astype(np.uint8)


def point_colors(mode: str, rgb: np.ndarray, normals: np.ndarray, depth_m: np.ndarray, dynamic: np.ndarray,
                 depth_limits: tuple[float, float]) -> np.ndarray:
    """Colours (N, 3) uint8 for N points in the given mode (a value of COLOR_MODES).

    rgb (N, 3) uint8, normals (N, 3) unit, depth_m (N,) depth of each point along its frame's
    camera axis, dynamic (N,) bool.
    """
    if mode == "rgb":
        return np.asarray(rgb, np.uint8)
    if mode == "normal":
        return colorize_normals(normals)
    if mode == "depth":
        return colorize_depth(depth_m, *depth_limits)
    if mode == "dynamic":
        return colorize_dynamic(dynamic)
    raise ValueError(f"unknown colour mode {mode!r}; choose one of {list(COLOR_MODES.values())}")
