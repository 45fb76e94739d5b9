"""A ray-cast tabletop of coloured boxes with known rigid motions (no simulator): the object layer's
test scene.

:func:`box_episode` renders, per frame, a checkered table z = 0 and boxes given by centre (world,
metres), yaw about +z (radians), half extents and colour, seen by one static camera: exact RGB, metric
depth, camera-frame normals, a segmentation (``seg_id_to_name``: the boxes' names; boxes named
``panda_*`` count as the robot, not as objects) and the recorded poses of the named objects
(``object_poses``, xyz + wxyz). Tests and benchmarks import it with ``tests/`` on ``sys.path``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d.testing.synthetic_scene import look_at_pose
from tesseract4d.dataset_format import CameraFrames, Episode

TABLE_ID = 1


@dataclass
class Box:
    name: str
    centre: np.ndarray  # (T, 3) world metres, per frame
    yaw_rad: np.ndarray  # (T,) per frame
    half_m: tuple[float, float, float]
    rgb: tuple[int, int, int]
    shown: np.ndarray | None = None  # (T,) bool: drawn in that frame (default: every frame)


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box_episode(boxes: list[Box], num_frames: int, size: int = 128, eye=(0.30, -0.30, 0.32),
                target=(0.0, 0.0, 0.02), fov_deg: float = 50.0, instruction: str = "push the red cube forward",
                intent: dict | None = None) -> Episode:
    """Render the boxes over ``num_frames`` frames of ``size``² pixels (see the module docstring)."""
    f = 0.5 * size / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], np.float64)
    T_world_cam = look_at_pose(np.asarray(eye, np.float64), np.asarray(target, np.float64))
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    rays = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], -1) @ T_world_cam[:3, :3].T  # (H, W, 3)
    origin = T_world_cam[:3, 3]
    rgb = np.zeros((num_frames, size, size, 3), np.uint8)
    depth = np.zeros((num_frames, size, size), np.float32)
    normal_cam = np.zeros((num_frames, size, size, 3), np.float32)
    seg = np.zeros((num_frames, size, size), np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_plane = np.where(rays[..., 2] < 0, -origin[2] / rays[..., 2], np.inf)
    p = origin + np.where(np.isfinite(s_plane), s_plane, 0)[..., None] * rays
    checker = ((np.floor(p[..., 0] / 0.05) + np.floor(p[..., 1] / 0.05)) % 2).astype(bool)
    table_rgb = np.where(checker[..., None], [170, 140, 100], [150, 120, 85])
    for t in range(num_frames):
        best = s_plane.copy()
        rgb[t] = table_rgb
        seg[t] = np.where(np.isfinite(s_plane), TABLE_ID, 0)
        n_world = np.zeros((size, size, 3))
        n_world[np.isfinite(s_plane)] = (0.0, 0.0, 1.0)
        for i, box in enumerate(boxes):
            if box.shown is not None and not box.shown[t]:
                continue
            R = _yaw(box.yaw_rad[t])
            o = (origin - box.centre[t]) @ R  # ray origin in the box frame
            d = rays @ R
            half = np.asarray(box.half_m)
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-half - o) / d, (half - o) / d
            near = np.nanmax(np.minimum(t1, t2), -1)
            far = np.nanmin(np.maximum(t1, t2), -1)
            hit = (near <= far) & (near > 0) & (near < best)
            axis = np.argmax(np.minimum(t1, t2), -1)
            n_box = np.eye(3)[axis] * -np.sign(np.take_along_axis(d, axis[..., None], -1))
            best = np.where(hit, near, best)
            rgb[t][hit] = box.rgb
            seg[t][hit] = i + 2
            n_world[hit] = (n_box @ R.T)[hit]
        depth[t] = np.where(np.isfinite(best), best, 0.0)
        normal_cam[t] = n_world @ T_world_cam[:3, :3]
    poses = {}
    for box in boxes:
        if box.name.startswith("panda_"):
            continue
        half_yaw = box.yaw_rad / 2
        poses[box.name] = np.concatenate([box.centre, np.cos(half_yaw)[:, None], np.zeros((num_frames, 2)),
                                          np.sin(half_yaw)[:, None]], 1).astype(np.float32)
    names = {0: "background", TABLE_ID: "table-workspace", **{i + 2: b.name for i, b in enumerate(boxes)}}
    cam = CameraFrames(rgb=rgb, depth_m=depth, normal_cam=normal_cam, K=np.repeat(K[None], num_frames, 0),
                       T_world_cam=np.repeat(T_world_cam[None], num_frames, 0), segmentation=seg, seg_id_to_name=names)
    return Episode(env_id="SyntheticBoxes-v0", seed=0, instruction=instruction, cameras={"close": cam},
                   frame_steps=np.arange(num_frames, dtype=np.int32), fps=10.0, source="simulation",
                   object_poses=poses, intent=intent)


def still(xyz, num_frames: int) -> np.ndarray:
    """(T, 3) a position held for every frame."""
    return np.repeat(np.asarray(xyz, np.float64)[None], num_frames, 0)


def moving(start, end, num_frames: int, first: int = 0, last: int | None = None) -> np.ndarray:
    """(T, 3) from ``start`` to ``end`` in equal steps between frames ``first`` and ``last``, held outside."""
    last = num_frames - 1 if last is None else last
    s = np.clip((np.arange(num_frames) - first) / max(last - first, 1), 0, 1)[:, None]
    return np.asarray(start, np.float64) + s * (np.asarray(end, np.float64) - np.asarray(start, np.float64))
