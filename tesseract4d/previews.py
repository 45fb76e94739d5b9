"""Browser-playable MP4 previews: RGB | depth (colour-mapped) | normal, side by side.

Depth and normals are coloured as in the viewer (:mod:`tesseract4d.colors`), with one depth
range over the whole clip so a clip's colours are comparable across its frames.

H.264 in yuv420p through imageio-ffmpeg, so browsers play them. Small frames are scaled up
(nearest neighbour) to at least ``MIN_PREVIEW_HEIGHT`` pixels so a person can see them.
Several futures of one scene play side by side, each under its caption (the instruction), in
one MP4 (:func:`write_side_by_side`; captions drawn with OpenCV).
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
# Captions (OpenCV Hershey simplex): font scale, pixels per line of text and around the lines.
CAPTION_FONT_SCALE, CAPTION_LINE_PX, CAPTION_PAD_PX = 0.6, 22, 6


def preview_frames(episode: Episode, camera: str | None = None,
                   depth_limits: tuple[float, float] | None = None) -> np.ndarray:
    """(T, H', 3W', 3) uint8 side-by-side frames of one camera (the first one by default).
    depth_limits: (near, far) metres of the depth colours (default: the clip's own range)."""
    cam = _camera(episode, camera)
    near, far = depth_limits or depth_range(cam.depth_m)
    panel = np.concatenate([cam.rgb, colorize_depth(cam.depth_m, near, far), colorize_normals(cam.normal_cam)], axis=2)
    scale = max(1, -(-MIN_PREVIEW_HEIGHT // panel.shape[1]))
    panel = panel.repeat(scale, axis=1).repeat(scale, axis=2)
    # H.264 with yuv420p needs even sizes; macro blocks of 16 avoid ffmpeg's resize warning.
    h, w = panel.shape[1:3]
    pad_h, pad_w = (-h) % 16, (-w) % 16
    if pad_h or pad_w:
        panel = np.pad(panel, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)))
    return panel


def _camera(episode: Episode, camera: str | None):
    return episode.cameras[camera or next(iter(episode.cameras))]


def write_preview(root: str | os.PathLike, episode: Episode, camera: str | None = None,
                  fps: float = PREVIEW_FPS) -> Path:
    """Write ``previews/<env_id>/seed_<seed>.mp4`` atomically; returns its path."""
    return write_mp4(preview_path(root, episode.env_id, episode.seed, episode.variant), preview_frames(episode, camera), fps)


def side_by_side_frames(episodes: list[Episode], captions: list[str], camera: str | None = None) -> np.ndarray:
    """(T, B + H', n*W', 3) uint8: the previews of ``episodes`` (each RGB | depth | normal, see
    :func:`preview_frames`) side by side, each under a band with its caption (e.g. the
    instruction that made that future). T is the longest episode's; a shorter one holds its last
    frame, and the depth colours share one range. The previews must have one size (episodes of one
    resolution do)."""
    if len(episodes) != len(captions) or not episodes:
        raise ValueError(f"{len(episodes)} episodes for {len(captions)} captions; give one caption per episode")
    # One depth range for all, so equal colours mean equal depths across the futures.
    limits = depth_range(np.concatenate([_camera(e, camera).depth_m.ravel() for e in episodes]))
    panels = [preview_frames(e, camera, limits) for e in episodes]
    if len({p.shape[1:] for p in panels}) != 1:
        raise ValueError(f"previews of different sizes {[p.shape[1:3] for p in panels]}; give episodes of one resolution")
    T, width = max(len(p) for p in panels), panels[0].shape[2]
    lines = [_wrap(c, width) for c in captions]
    band_h = -(-(CAPTION_PAD_PX * 2 + CAPTION_LINE_PX * max(len(ls) for ls in lines)) // 16) * 16  # macro blocks of 16
    halves = []
    for panel, text in zip(panels, lines):
        band = _caption_band(text, band_h, width)  # (B, W', 3)
        frames = panel[np.minimum(np.arange(T), len(panel) - 1)]  # (T, H', W', 3)
        halves.append(np.concatenate([np.broadcast_to(band, (T, *band.shape)), frames], axis=1))
    return np.concatenate(halves, axis=2)


def write_side_by_side(path: str | os.PathLike, episodes: list[Episode], captions: list[str], camera: str | None = None,
                       fps: float = PREVIEW_FPS) -> Path:
    """Write :func:`side_by_side_frames` as an MP4 at ``path`` (atomically); returns the path."""
    return write_mp4(Path(path), side_by_side_frames(episodes, captions, camera), fps)


def _wrap(text: str, width: int) -> list[str]:
    """``text`` broken into lines that fit ``width`` pixels in the caption font."""
    import cv2

    lines: list[str] = []
    for word in text.split():
        trial = f"{lines[-1]} {word}" if lines else word
        fits = cv2.getTextSize(trial, cv2.FONT_HERSHEY_SIMPLEX, CAPTION_FONT_SCALE, 1)[0][0] <= width - 2 * CAPTION_PAD_PX
        if lines and fits:
            lines[-1] = trial
        else:
            lines.append(word)
    return lines or [""]


def _caption_band(lines: list[str], height: int, width: int) -> np.ndarray:
    """(height, width, 3) uint8: white lines of text on a dark band."""
    import cv2

    band = np.full((height, width, 3), 24, np.uint8)
    text_h = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, CAPTION_FONT_SCALE, 1)[0][1]
    for i, line in enumerate(lines):
        baseline = CAPTION_PAD_PX + i * CAPTION_LINE_PX + (CAPTION_LINE_PX + text_h) // 2  # centred in its line
        cv2.putText(band, line, (CAPTION_PAD_PX, baseline), cv2.FONT_HERSHEY_SIMPLEX, CAPTION_FONT_SCALE,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return band


def write_mp4(path: Path, frames: np.ndarray, fps: float = PREVIEW_FPS) -> Path:
    """Write (T, H, W, 3) uint8 frames (H, W multiples of 16) as browser-playable H.264 at ``path``,
    through a temporary sibling renamed into place; returns ``path``."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.partial.mp4")
    try:
        writer = imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", pixelformat="yuv420p",
                                    macro_block_size=16, ffmpeg_log_level="error", output_params=["-crf", "20"])
        with writer:
            for frame in frames:
                writer.append_data(frame)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
