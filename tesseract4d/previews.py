"""Browser-playable MP4 previews: RGB | depth (colour-mapped) | normal, side by side.

H.264 in yuv420p through imageio-ffmpeg, so browsers play them. Small frames are scaled up
(nearest neighbour) to at least ``MIN_PREVIEW_HEIGHT`` pixels so a person can see them.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from tesseract4d.dataset_format import Episode, preview_path

MIN_PREVIEW_HEIGHT = 192
PREVIEW_FPS = 8.0


def depth_to_color(depth_m: np.ndarray, near_m: float | None = None, far_m: float | None = None) -> np.ndarray:
    """(T, H, W) metres -> (T, H, W, 3) uint8 with OpenCV's TURBO map; 0 (no hit) is black.

    The range defaults to the valid depths' 2nd..90th percentile (the far
    background would otherwise take most of the colour range) over the whole clip, so a
    clip's colours are comparable across its frames.
    """
    import cv2

    valid = depth_m > 0
    if near_m is None or far_m is None:
        vals = depth_m[valid]
        near_m, far_m = (np.percentile(vals, [2, 90]) if vals.size else (0.0, 1.0))
    scale = np.clip((depth_m - near_m) / max(far_m - near_m, 1e-6), 0, 1)
    gray = (255 * (1 - scale)).astype(np.uint8)  # near = warm
    out = np.stack([cv2.applyColorMap(g, cv2.COLORMAP_TURBO)[..., ::-1] for g in gray])
    out[~valid] = 0
    return out


def normal_to_color(normal_cam: np.ndarray) -> np.ndarray:
    """(…, 3) unit normals in [-1, 1] -> uint8 RGB (n + 1) / 2; no-hit zeros stay black."""
    rgb = ((np.asarray(normal_cam, np.float32) + 1) * 127.5).clip(0, 255).astype(np.uint8)
    rgb[np.all(normal_cam == 0, axis=-1)] = 0
    return rgb


def preview_frames(episode: Episode, camera: str | None = None) -> np.ndarray:
    """(T, H', 3W', 3) uint8 side-by-side frames of one camera (the first one by default)."""
    name = camera or next(iter(episode.cameras))
    cam = episode.cameras[name]
    panel = np.concatenate([cam.rgb, depth_to_color(cam.depth_m), normal_to_color(cam.normal_cam)], axis=2)
    scale = max(1, -(-MIN_PREVIEW_HEIGHT // panel.shape[1]))
    panel = panel.repeat(scale, axis=1).repeat(scale, axis=2)
    # H.264 with yuv420p needs even sizes; macro blocks of 16 avoid ffmpeg's resize warning.
    h, w = panel.shape[1:3]
    pad_h, pad_w = (-h) % 16, (-w) % 16
    if pad_h or pad_w:
        panel = np.pad(panel, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)))
    return panel


def write_preview(root: str | os.PathLike, episode: Episode, camera: str | None = None,
                  fps: float = PREVIEW_FPS) -> Path:
    """Write ``previews/<env_id>/seed_<seed>.mp4`` atomically; returns its path."""
    import imageio.v2 as imageio

    final = preview_path(root, episode.env_id, episode.seed, episode.variant)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.stem}.{uuid.uuid4().hex}.partial.mp4")
    frames = preview_frames(episode, camera)
    try:
        writer = imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", pixelformat="yuv420p",
                                    macro_block_size=16, ffmpeg_log_level="error", output_params=["-crf", "20"])
        with writer:
            for frame in frames:
                writer.append_data(frame)
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return final
