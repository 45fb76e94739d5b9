"""The gripper's track through a clip: where the gripper is in each frame (world metres), read from
the clip's RGB-D and its object layer.

A predicted clip at 128² often loses the small object the arm moves (it smears and vanishes under the
arriving gripper) while the arm itself stays sharp: the arm is the large, grey-white, moving thing of the
scene. Robot4DGen executes the gripper it tracks in generated RGB-D; here the track tells the goal reading
where a lost object went (:mod:`tesseract4d.policy.goal_reading`).

The arm in a frame is what the object layer leaves over (:class:`reconstruction.objects.ObjectLayer`'s
``point_object``, -1 = no object) among the pixels that may be the arm (``reconstruction.objects.arm_pixels``:
moving, so the camera must stay still, and grey, white or black, where a blurred object's colours are
not), and lies more than ``ABOVE_TABLE_M`` above the table top (a predicted clip redraws a white target
disc on the table a little nearer now and then). Isolated points (fewer than ``MIN_NEIGHBOURS`` within
``NEIGHBOUR_M``) are noise. The gripper's point is the hand: the arm's points within ``HAND_BAND_M`` above its lowest (``LOW_QUANTILE``) height along
the scene's up axis; in the table plane their median, along up their ``HEIGHT_QUANTILE``. Its offset from
the TCP differs with the view (the fingers hide behind the hand or the object they push), so the goal
reading uses only its displacements.

Chosen against the simulator's TCP (forward kinematics of the stored joint positions, for the check only)
on the true frames of the 48 held-out episodes (128², ``close`` camera), displacements from the fifth
frame on: in the table plane median 3 mm, 90th percentile 13 mm; along up median 4 mm, 90th percentile
14 mm. The fingers alone (the lowest 1.5 cm of the arm) were worse in the plane: median 11 mm, 90th
percentile 51 mm (they hide behind the hand or the pushed object in many frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruction.objects import arm_pixels, static_depth
from tesseract4d.geometry import scene_up_axis, transform_points, unproject_depth
from tesseract4d.policy.perception import TABLE_Z_M

ABOVE_TABLE_M = 0.015  # arm points lie at least this high above the table top (lower: the table's own markings)
MIN_ARM_POINTS = 12  # fewer arm points in a frame: the arm is not seen there (NaN)
NEIGHBOUR_M = 0.015  # an arm point needs MIN_NEIGHBOURS others this close ...
MIN_NEIGHBOURS = 4  # ... or it is depth noise
LOW_QUANTILE = 0.02  # the arm's lowest height, robust to a stray point
HAND_BAND_M = 0.16  # the hand: the arm's points this close above its lowest height ...
HEIGHT_QUANTILE = 0.1  # ... its height: this quantile of theirs (the median in the table plane)


@dataclass
class GripperTrack:
    """The gripper's point per frame (world metres) and how many arm points each frame had."""

    gripper_world_m: np.ndarray  # (T, 3); NaN where the arm is not seen
    arm_points: np.ndarray  # (T,) int
    up: np.ndarray  # (3,) the scene's up axis

    def seen(self) -> np.ndarray:
        """(T,) bool: frames where the gripper is seen."""
        return np.isfinite(self.gripper_world_m).all(axis=1)


def gripper_point(points_world: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """(3,) the gripper's point of an arm given as points (N, 3) (world metres; see the module docstring),
    or None when too few are left after dropping isolated ones."""
    from scipy.spatial import cKDTree  # scipy loads with the tracker only

    p = np.asarray(points_world, np.float64)
    p = p[p @ up >= TABLE_Z_M + ABOVE_TABLE_M]
    if len(p) < MIN_ARM_POINTS:
        return None
    # MIN_NEIGHBOURS others within NEIGHBOUR_M: the (MIN_NEIGHBOURS + 1)-th nearest point (itself the first) is
    # that close (a k-nearest query; counting every point in the ball cost ten times as much)
    dist, _ = cKDTree(p).query(p, k=MIN_NEIGHBOURS + 1, distance_upper_bound=NEIGHBOUR_M)
    p = p[np.isfinite(dist[:, -1])]
    if len(p) < MIN_ARM_POINTS:
        return None
    h = p @ up
    hand = p[h <= float(np.quantile(h, LOW_QUANTILE)) + HAND_BAND_M]
    h_hand = hand @ up
    flat = hand - np.outer(h_hand, up)  # (N, 3) in the table plane
    return np.median(flat, axis=0) + float(np.quantile(h_hand, HEIGHT_QUANTILE)) * up


def track_gripper(rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, layer) -> GripperTrack | None:
    """The gripper's track through a clip. rgb (T, H, W, 3) uint8, depth_m (T, H, W) metres, K (T, 3, 3),
    T_world_cam (T, 4, 4); ``layer``: the clip's object layer with ``point_object`` labels (every valid
    pixel, pixel order). None when the camera moves (what moves cannot be told from the background) or
    the layer has no labels."""
    depth = np.asarray(depth_m, np.float32)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    static = static_depth(depth, valid, T_world_cam)  # (H, W); None when the camera moves
    if static is None or len(layer.point_object) != len(depth):
        return None
    up = scene_up_axis(T_world_cam[0])
    points = np.full((len(depth), 3), np.nan)
    counts = np.zeros(len(depth), int)
    for t in range(len(depth)):
        label = np.full(depth.shape[1:], -1, np.int32)
        label[valid[t]] = layer.point_object[t]
        arm = arm_pixels(rgb[t], depth[t], valid[t], static) & (label < 0)  # moving, grey, of no object
        counts[t] = int(arm.sum())
        pts = transform_points(T_world_cam[t], unproject_depth(depth[t], K[t])[arm])
        point = gripper_point(pts, up)
        if point is not None:
            points[t] = point
    return GripperTrack(points, counts, up)
