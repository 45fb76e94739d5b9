"""Best of several noise draws: keep the future whose objects keep their colours.

One noise draw decides much of a future (docs/research/sampling.md, "The best of several noise
draws"): in some draws a cube the arm reaches stays a cube, in others it turns into a blob of the
other objects' colours or fades. With ``draws`` N > 1 the sampler predicts each scene from N noises
and keeps the future that :func:`objects_kept` scores highest. The score reads only the given first
frame (its RGB, and its segmentation where it has one) and the predicted clip, never anything of the
true future:

    for each scene object visible in frame 0 (named by the segmentation, or found by its colour in a
    frame without one: object_finder.py), its distinctive colours there (object_colours.py); in
    every later frame, the predicted pixels of those colours within ``WINDOW_PX`` of the object's
    frame-0 box, as a share of frame 0's, capped at 1; the mean over frames, then over objects.

An object that moves whole keeps its score, one hidden by the arm loses it in every draw alike, one
that fades or changes colour loses it in the draws where it does. Draw 0 is the noise a single draw
uses, so ``draws`` 1 is the sampler without a choice. N draws cost N times the sampling.

A first frame in which no object is found has nothing to follow: such a scene keeps draw 0.
"""

from __future__ import annotations

import numpy as np

from tesseract4d.object_colours import MIN_OBJECT_PIXELS, distinctive, matches
from tesseract4d.object_finder import find_objects
from tesseract4d.segments import scene_object_ids
from tesseract4d.errors import UserError

# How far (pixels) around an object's frame-0 box its colours are counted in later frames: about the
# distance a pushed cube travels in a 128² clip of the close camera.
WINDOW_PX = 24
# The pixels next to an object (outside it) whose colours make its own colours not distinctive.
AROUND_PX = 2
# At most this many of an object's distinctive colours are compared (evenly spaced), to bound the cost.
MAX_PALETTE = 64


def check_draws(draws: int) -> int:
    """``draws`` as an int, refused with the fix when it is below 1."""
    if int(draws) < 1:
        raise UserError(f"--draws must be at least 1 (1 = a single noise draw), got {draws}")
    return int(draws)


def draw_noise_seed(seed: int, draw: int) -> int:
    """The noise seed of draw ``draw`` of a scene whose single draw uses ``seed`` (draw 0: ``seed``)."""
    return int(seed) if draw == 0 else (int(seed) * 7_919 + 104_729 * int(draw)) % (1 << 62)


def object_windows(first_rgb: np.ndarray, segmentation: np.ndarray | None = None,
                   seg_id_to_name: dict | None = None) -> list[tuple]:
    """The objects :func:`objects_kept` follows: (palette (N, 3), window (y0, y1, x0, x1), frame-0
    count) for each scene object with at least ``MIN_OBJECT_PIXELS`` (object_colours.py) distinctive pixels in
    frame 0. The objects are the segmentation's (with its ``seg_id_to_name``) or, without one, those
    :func:`~tesseract4d.object_finder.find_objects` finds in ``first_rgb``."""
    if segmentation is None:
        masks = find_objects(first_rgb)
    else:
        seg = np.asarray(segmentation)
        masks = [seg == oid for oid in scene_object_ids(seg_id_to_name or {})]
    rgb = np.asarray(first_rgb, np.float32)
    H, W = rgb.shape[:2]
    out = []
    for mask in masks:
        if mask.sum() < MIN_OBJECT_PIXELS:
            continue
        palette = rgb[mask][distinctive(rgb, mask, AROUND_PX)]
        if len(palette) < MIN_OBJECT_PIXELS:
            continue
        # Evenly spaced, then each colour once: a flat-shaded face repeats one colour many times.
        palette = np.unique(palette[:: -(-len(palette) // MAX_PALETTE)], axis=0)
        ys, xs = np.nonzero(mask)
        y0, y1 = max(0, ys.min() - WINDOW_PX), min(H, ys.max() + WINDOW_PX + 1)
        x0, x1 = max(0, xs.min() - WINDOW_PX), min(W, xs.max() + WINDOW_PX + 1)
        count0 = int(matches(rgb[y0:y1, x0:x1], palette).sum())
        if count0 >= MIN_OBJECT_PIXELS:
            out.append((palette, (y0, y1, x0, x1), count0))
    return out


def objects_kept(windows: list[tuple], clip_rgb: np.ndarray) -> float:
    """How well a predicted clip (T, H, W, 3) keeps the objects of :func:`object_windows` in their
    colours near where they were, in [0, 1]; NaN when there is no object to follow or no later frame."""
    rgb = np.asarray(clip_rgb, np.float32)
    if not windows or len(rgb) < 2:
        return float("nan")
    per_object = []
    for palette, (y0, y1, x0, x1), count0 in windows:
        kept = [min(1.0, matches(frame[y0:y1, x0:x1], palette).sum() / count0) for frame in rgb[1:]]
        per_object.append(float(np.mean(kept)))
    return float(np.mean(per_object))


def choose(windows: list[tuple], candidates: list[np.ndarray]) -> tuple[int, list[float]]:
    """(index of the candidate clip to keep, every candidate's score): the highest score, the
    earliest draw on a tie; draw 0 when no candidate can be scored."""
    scores = [objects_kept(windows, c) for c in candidates]
    finite = [s if np.isfinite(s) else -np.inf for s in scores]
    best = int(np.argmax(finite)) if np.isfinite(max(finite)) else 0
    return best, scores
