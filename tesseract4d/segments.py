"""Segmentation names: which segments of a rendered episode are scenery, the robot or the scene's objects.

A ManiSkill episode's segmentation maps each pixel to a segment id and ``seg_id_to_name`` names the
ids (``panda_link3``, ``cube_a``, ``table-workspace``, ...). Two readings of it are used:

- robot and objects (:func:`robot_object_mask`): every named segment but the scenery; the autoencoder
  and the latent model weight these pixels up.
- the scene's objects (:func:`scene_object_ids`, :func:`scene_object_mask`): what a task moves or
  leaves standing (cubes, cylinders), not the robot, the table, the ground, the background or a goal
  marker; held-out evaluation looks for these, and the latent model can weight them up apart
  from the much larger robot.
"""

from __future__ import annotations

import numpy as np

# Segmentation names that are scenery; every other named segment is the robot or an object.
SCENERY_SEGMENTS = frozenset({"background", "ground", "table-workspace", "goal_site"})
# Names (prefixes) in a segmentation map that are not scene objects.
NOT_OBJECTS = ("background", "table", "ground", "panda_", "camera_", "goal")


def robot_object_mask(segmentation: np.ndarray, seg_id_to_name: dict[int, str]) -> np.ndarray:
    """(..., H, W) bool: pixels whose segment is the robot or an object (not scenery)."""
    ids = [i for i, n in seg_id_to_name.items() if n not in SCENERY_SEGMENTS]
    return np.isin(segmentation, np.asarray(ids, dtype=segmentation.dtype))


def scene_object_ids(seg_id_to_name: dict) -> list[int]:
    """Segmentation ids of the scene's objects (not robot links, table, ground, background, goal)."""
    return sorted(int(i) for i, n in seg_id_to_name.items() if not str(n).startswith(NOT_OBJECTS))


def scene_object_mask(segmentation: np.ndarray, seg_id_to_name: dict) -> np.ndarray:
    """(..., H, W) bool: pixels of the scene's objects (:func:`scene_object_ids`)."""
    return np.isin(segmentation, np.asarray(scene_object_ids(seg_id_to_name), dtype=segmentation.dtype))
