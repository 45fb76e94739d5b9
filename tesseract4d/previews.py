"""Browser-playable MP4 previews: RGB | depth (colour-mapped) | normal, side by side.

Depth and normals are coloured as in the viewer (:mod:`tesseract4d.colors`), with one depth
range over the whole clip so a clip's colours are comparable across its frames.

H.264 in yuv420p through imageio-ffmpeg, so browsers play them. Small frames are scaled up
(nearest neighbour) to at least ``MIN_PREVIEW_HEIGHT`` pixels so a person can see them.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from tesseract4d.colors import colorize_depth, colorize_normals, depth_range
from tesseract4d.dataset_format import Episode, preview_path

MIN_PREVIEW_HEIGHT = 192
PREVIEW_FPS = 8.0


def preview_frames(episode: Episode, camera: str | None = None) -> np.ndarray:
    """(T, H', 3W', 3) uint8 side-by-side frames of one camera (the first one by default)."""
    name = camera or next(iter(episode.cameras))
    cam = episode.cameras[name]
    panel = np.concatenate([cam.rgb, colorize_depth(cam.depth_m, *depth_range(cam.depth_m)), colorize_normals(cam.normal_cam)], axis=2)
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
