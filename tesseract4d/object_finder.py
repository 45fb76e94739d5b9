"""The scene's objects found in one RGB frame alone, for first frames that carry no segmentation.

A rendered dataset episode names its objects in a segmentation; a frame from image files
(`predict --rgb`), a closed-loop observation or a reconstruction does not. The scenes' objects are
small cubes and cylinders of saturated colours on a wooden table beside a white robot and a grey
floor, so they can be found by colour:

1. candidates: saturated pixels (HSV saturation and value above a floor; the robot, the floor and
   the background are grey) whose colour lies farther than ``OBJECT_COLOUR_TOL`` from the median
   colour of a window about a third of the image wide around them (the table's colour there; an
   object fills a small part of such a window);
2. objects: the 8-connected groups of candidates of at least ``MIN_OBJECT_PIXELS`` and at most
   ``MAX_OBJECT_SHARE`` of the image, of which at least ``MIN_DISTINCTIVE_SHARE`` of the pixels are
   unlike every pixel just around the group (object_colours.py: a sliver of table between the robot's
   feet, a grain streak or the table's edge against the floor are like the table beside them).

On the held-out sets' first frames (48 tabletop, 48 cube-task) this finds every scene object whose
colours the segmentation-based reading follows, all of its distinctive pixels in one group (the
whole object but for a red cylinder's dark side, as like the table as unlike it: mean IoU with the
masks 0.85 and 0.89), and nothing else. On 3 of 23 training cube-task first frames it also took a piece of
a goal target's red ring for an object: the target stays put, so it scores every draw alike but where the
arm covers it. Images are (H, W, 3) RGB.
"""

from __future__ import annotations

import numpy as np

from tesseract4d.object_colours import MIN_OBJECT_PIXELS, OBJECT_COLOUR_TOL, distinctive

# HSV floors (OpenCV's 0-255 scale) below which a pixel is grey: the robot, the floor, the background.
MIN_SATURATION = 90
MIN_VALUE = 50
# The median window's width as a share of the image's smaller side (41 px at 128²; made odd).
BACKGROUND_WINDOW_SHARE = 0.32
# A group larger than this share of the image is scenery (the table), not an object.
MAX_OBJECT_SHARE = 0.03
# The share of a group's pixels that must be unlike its surroundings, and how far around it looks.
MIN_DISTINCTIVE_SHARE = 0.3
AROUND_PX = 2


def find_objects(rgb: np.ndarray) -> list[np.ndarray]:
    """(H, W) bool masks of the objects found in ``rgb`` (H, W, 3), largest first; [] when none."""
    import cv2

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"find_objects needs an (H, W, 3) RGB image, got shape {rgb.shape}")
    rgb = np.clip(np.rint(rgb), 0, 255).astype(np.uint8) if rgb.dtype != np.uint8 else rgb
    H, W = rgb.shape[:2]
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    window = max(3, int(round(BACKGROUND_WINDOW_SHARE * min(H, W))) | 1)
    background = cv2.medianBlur(rgb, window).astype(np.float32)
    unlike = np.linalg.norm(rgb.astype(np.float32) - background, axis=-1) > OBJECT_COLOUR_TOL
    candidates = unlike & (hsv[..., 1] >= MIN_SATURATION) & (hsv[..., 2] >= MIN_VALUE)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(candidates.astype(np.uint8), connectivity=8)
    found = []
    for i in range(1, count):
        area = int(stats[i, cv2.CC_STAT_AREA])
        if not MIN_OBJECT_PIXELS <= area <= MAX_OBJECT_SHARE * H * W:
            continue
        mask = labels == i
        own = distinctive(rgb, mask, AROUND_PX)
        if own.mean() >= MIN_DISTINCTIVE_SHARE and own.sum() >= MIN_OBJECT_PIXELS:
            found.append(mask)
    return sorted(found, key=lambda m: -int(m.sum()))
