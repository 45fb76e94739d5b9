"""The hand's track from a clip's depth: a grey box (the hand) moving over a table, rendered by ray casting
from an oblique camera; the object layer labels a red cube on the table."""

from __future__ import annotations

import numpy as np

from reconstruction.hand_track import gripper_point, track_gripper
from reconstruction.objects import ObjectLayer

H = W = 96
TABLE_RGB, HAND_RGB, CUBE_RGB = (150, 90, 50), (200, 200, 205), (200, 30, 30)


def camera() -> tuple[np.ndarray, np.ndarray]:
    """K and T_world_cam (OpenCV axes) of a camera at (0.6, 0, 0.6) looking at the origin."""
    eye, target = np.array([0.6, 0.0, 0.6]), np.zeros(3)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    K = np.array([[120.0, 0, W / 2], [0, 120.0, H / 2], [0, 0, 1]])
    return K, T


def render(boxes, K, T_world_cam):
    """rgb (H, W, 3) and depth_m (H, W) of the table (z = 0) and axis-aligned boxes [(lo, hi, rgb)]."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z_cam = 1
    d = d_cam @ T_world_cam[:3, :3].T  # (H, W, 3) world direction per unit camera depth
    o = T_world_cam[:3, 3]
    depth = np.where(d[..., 2] < 0, -o[2] / np.minimum(d[..., 2], -1e-9), np.inf)
    rgb = np.broadcast_to(np.array(TABLE_RGB, np.uint8), (H, W, 3)).copy()
    for lo, hi, colour in boxes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
        near, far = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
        hit = (near <= far) & (near > 0) & (near < depth)
        depth[hit] = near[hit]
        rgb[hit] = colour
    return rgb, depth.astype(np.float32)


def test_the_track_follows_a_moving_hand_and_ignores_the_labelled_object():
    K, T_world_cam = camera()
    cube = ((0.0, 0.1, 0.0), (0.04, 0.14, 0.04), CUBE_RGB)
    hand_xy = [(0.0, -0.1 + 0.015 * t) for t in range(8)]
    frames = [render([cube, ((x - 0.03, y - 0.03, 0.06), (x + 0.03, y + 0.03, 0.2), HAND_RGB)], K, T_world_cam)
              for x, y in hand_xy]
    frames.append(render([cube], K, T_world_cam))  # the hand gone: the clip's background everywhere
    rgb = np.stack([f[0] for f in frames])
    depth = np.stack([f[1] for f in frames])
    labels = [np.where((f[0] == CUBE_RGB).all(-1), 0, -1)[np.isfinite(f[1])].astype(np.int16) for f in frames]
    layer = ObjectLayer([], source="test", point_object=labels)
    n = len(frames)
    track = track_gripper(rgb, depth, np.repeat(K[None], n, 0), np.repeat(T_world_cam[None], n, 0), layer)
    seen = track.seen()
    assert seen[:8].all() and not seen[8]
    moved = track.gripper_world_m[:8] - track.gripper_world_m[0]
    np.testing.assert_allclose(moved[:, :2], np.array(hand_xy) - hand_xy[0], atol=0.006)
    np.testing.assert_allclose(moved[:, 2], 0.0, atol=0.006)


def test_a_moving_camera_gives_no_track():
    K, T_world_cam = camera()
    rgb, depth = render([], K, T_world_cam)
    T2 = T_world_cam.copy()
    T2[0, 3] += 0.1
    layer = ObjectLayer([], source="test", point_object=[np.zeros(int(np.isfinite(depth).sum()), np.int16)] * 2)
    assert track_gripper(np.stack([rgb, rgb]), np.stack([depth, depth]), np.stack([K, K]), np.stack([T_world_cam, T2]),
                         layer) is None


def test_points_on_the_table_and_stray_points_are_not_the_arm():
    rng = np.random.default_rng(0)
    hand = rng.uniform([0.1, 0.1, 0.05], [0.14, 0.14, 0.2], (400, 3))
    table_marks = np.c_[rng.uniform(-0.2, 0.2, (300, 2)), np.full(300, 0.003)]  # a white disc redrawn on the table
    strays = rng.uniform([-0.3, -0.3, 0.02], [-0.2, -0.2, 0.03], (3, 3))
    point = gripper_point(np.concatenate([hand, table_marks, strays]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(point[:2], [0.12, 0.12], atol=0.01)
    assert 0.05 <= point[2] <= 0.08
