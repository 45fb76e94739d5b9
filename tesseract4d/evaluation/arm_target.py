"""Which scene object a clip's arm goes to: the instructed one, or another.

The instruction contrast judges the instructed object's own motion. When it is wrong, the arm may
have gone to another object (the words' choice of object lost) or to the instructed one without
moving it the commanded way (the contact lost). This tells the two apart from a clip's RGB and
metric depth alone, the same way for the ground truth and for a prediction, with the ground truth's
first-frame segmentation, object poses and camera (a world with z up and a table, as ManiSkill's):

- **arm points**: pixels of frame t that differ from frame 0 (RGB by more than ``ARM_RGB_TOL`` in some
  channel, or depth by more than ``ARM_DEPTH_TOL_M``) whose world point lies ``ARM_BAND_M`` above the
  table: above the objects' tops, so a moved object's own pixels do not count, and below the arm's
  travel, so the arm passing high over the scene does not either;
- the arm **goes to** the scene object with the most arm points within ``ARM_NEAR_M`` (horizontally) of
  the object's first-frame position, summed over the clip; to none when no arm point comes near one.

The table's height is the median world height of the first frame's table pixels. On the held-out
tabletop groups (two noise draws, 66 active instructions) this finds the ground truth's arm at the
instructed object in 56, against 0.37 by chance (docs/research/evaluation.md, "Where a model fails").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tesseract4d.geometry import depth_to_world_points
from tesseract4d.segments import scene_object_ids

ARM_RGB_TOL = 40  # 0-255, any channel
ARM_DEPTH_TOL_M = 0.015
ARM_BAND_M = (0.05, 0.12)  # height above the table: above the cubes' tops (4 cm), below the arm's travel
ARM_NEAR_M = 0.03  # horizontal distance to an object's first-frame position
TABLE_PREFIX = "table"


@dataclass(frozen=True)
class ArmVisit:
    """``judged``: the scene could be measured (a table and at least one object with a pose in view);
    ``object``: the name of the object the arm goes to, None when none; ``points``: arm points near each
    object, summed over the clip."""

    judged: bool
    object: str | None = None
    points: dict = field(default_factory=dict)


def _frame(a: np.ndarray, t: int) -> np.ndarray:
    """Frame t of a per-frame (T, ...) camera array, or the array itself when it is one for all frames."""
    a = np.asarray(a, np.float64)
    return a[t] if a.ndim == 3 else a


def table_height_m(depth_m: np.ndarray, segmentation: np.ndarray, seg_id_to_name: dict, K: np.ndarray,
                   T_world_cam: np.ndarray) -> float | None:
    """Median world height of one frame's table pixels (names starting with "table"); None when no
    table pixel has depth."""
    ids = [int(i) for i, n in seg_id_to_name.items() if str(n).startswith(TABLE_PREFIX)]
    mask = np.isin(segmentation, ids) & (np.asarray(depth_m) > 0)
    if not mask.any():
        return None
    points, _ = depth_to_world_points(np.where(mask, depth_m, 0.0), K, T_world_cam)
    return float(np.median(points[:, 2]))


def arm_points_near(rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                    objects_xy: dict[str, np.ndarray], table_z_m: float) -> dict[str, int]:
    """Arm points (see the module docstring) within ``ARM_NEAR_M`` of each object's (x, y), summed over
    frames 1..T-1. rgb (T, H, W, 3) uint8; depth_m (T, H, W); K (3, 3) or (T, 3, 3); T_world_cam (4, 4)
    or (T, 4, 4)."""
    rgb = np.asarray(rgb).astype(np.int16)
    depth = np.asarray(depth_m, np.float32)
    names = list(objects_xy)
    xy = np.asarray([objects_xy[n][:2] for n in names], np.float64).reshape(-1, 2)
    counts = np.zeros(len(names), np.int64)
    low, high = table_z_m + ARM_BAND_M[0], table_z_m + ARM_BAND_M[1]
    for t in range(1, len(rgb)):
        changed = (np.abs(rgb[t] - rgb[0]).max(-1) > ARM_RGB_TOL) | (np.abs(depth[t] - depth[0]) > ARM_DEPTH_TOL_M)
        points, valid = depth_to_world_points(depth[t], _frame(K, t), _frame(T_world_cam, t))
        points = points[changed[valid]]
        points = points[(points[:, 2] > low) & (points[:, 2] < high)]
        if len(points) and len(names):
            d = np.hypot(points[:, None, 0] - xy[None, :, 0], points[:, None, 1] - xy[None, :, 1])
            counts += (d < ARM_NEAR_M).sum(0)
    return {n: int(c) for n, c in zip(names, counts)}


def arm_visit(gt, camera: str, rgb: np.ndarray, depth_m: np.ndarray) -> ArmVisit:
    """Where the arm of a clip (``rgb``, ``depth_m``: the ground truth's own or a prediction of it, frames
    matched by index) goes among the ground truth's scene objects visible in its first frame."""
    cam = gt.cameras[camera]
    if cam.segmentation is None:
        return ArmVisit(False)
    seg0 = np.asarray(cam.segmentation[0])
    table_z = table_height_m(np.asarray(cam.depth_m[0]), seg0, cam.seg_id_to_name, _frame(cam.K, 0),
                             _frame(cam.T_world_cam, 0))
    names = [cam.seg_id_to_name[i] for i in scene_object_ids(cam.seg_id_to_name) if (seg0 == i).any()]
    objects = {n: np.asarray(gt.object_poses[n][0, :2]) for n in names if n in gt.object_poses}
    if table_z is None or not objects:
        return ArmVisit(False)
    n = min(len(rgb), len(depth_m))
    points = arm_points_near(np.asarray(rgb)[:n], np.asarray(depth_m)[:n], cam.K, cam.T_world_cam, objects, table_z)
    best = max(points, key=points.get)
    return ArmVisit(True, best if points[best] > 0 else None, points)


__all__ = ["ARM_BAND_M", "ARM_NEAR_M", "ArmVisit", "arm_points_near", "arm_visit", "table_height_m"]
