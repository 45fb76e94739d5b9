"""Property tests of the pure camera geometry (tesseract4d/geometry.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tesseract4d.geometry import (
    depth_to_world_points, invert_pose, normals_from_depth, pixel_grid, project_points, rotate_vectors,
    transform_points, unproject_depth,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.linalg.det(q))  # a rotation, det +1
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.uniform(-2, 2, 3)
    return T


def intrinsics(f: float, w: int, h: int) -> np.ndarray:
    return np.array([[f, 0, w / 2], [0, f * 1.1, h / 2], [0, 0, 1.0]])


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_pose_inverse_is_identity(seed):
    T = random_pose(np.random.default_rng(seed))
    np.testing.assert_allclose(T @ invert_pose(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert_pose(invert_pose(T)), T, atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_transform_round_trip_and_rotation_keeps_length(seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    p = rng.uniform(-3, 3, (20, 3))
    np.testing.assert_allclose(transform_points(invert_pose(T), transform_points(T, p)), p, atol=1e-5)
    n = rng.standard_normal((20, 3))
    np.testing.assert_allclose(np.linalg.norm(rotate_vectors(T, n), axis=-1), np.linalg.norm(n, axis=-1), rtol=1e-5)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), f=st.floats(20.0, 200.0), h=st.integers(2, 24), w=st.integers(2, 24))
def test_project_unproject_identity(seed, f, h, w):
    depth = np.random.default_rng(seed).uniform(0.1, 5.0, (h, w))
    K = intrinsics(f, w, h)
    pts = unproject_depth(depth, K)
    uv, z = project_points(pts, K)
    u, v = pixel_grid(h, w)
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-3)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-3)
    np.testing.assert_allclose(z, depth, rtol=1e-6)


def test_depth_to_world_points_skips_missing_depth():
    depth = np.array([[1.0, 0.0], [np.nan, 2.0]])
    pts, valid = depth_to_world_points(depth, intrinsics(10, 2, 2), np.eye(4))
    assert valid.tolist() == [[True, False], [False, True]]
    assert pts.shape == (2, 3) and np.all(np.isfinite(pts))


@settings(max_examples=30, deadline=None)
@given(nx=finite, ny=finite, d=st.floats(0.5, 3.0))
def test_normals_from_depth_of_a_plane_equal_the_plane_normal(nx, ny, d):
    # Plane n . p = -d with n facing the camera (n_z < 0 in OpenCV axes, camera looks along +z).
    n = np.array([0.5 * nx, 0.5 * ny, -1.0])
    n /= np.linalg.norm(n)
    H = W = 16
    K = intrinsics(20.0, W, H)
    u, v = pixel_grid(H, W)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    depth = -d / (rays @ n)  # z of the ray's hit (ray z component is 1)
    normals = normals_from_depth(depth, K)
    lengths = np.linalg.norm(normals, axis=-1)
    np.testing.assert_allclose(lengths, 1.0, atol=1e-5)  # unit length everywhere (all pixels valid)
    np.testing.assert_allclose(normals.reshape(-1, 3) @ n, 1.0, atol=1e-4)


def test_normals_from_depth_zero_where_depth_missing():
    depth = np.ones((8, 8))
    depth[3, 3] = 0.0
    n = normals_from_depth(depth, intrinsics(10, 8, 8))
    assert np.all(n[3, 3] == 0)
    ok = np.linalg.norm(n, axis=-1) > 0
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=-1), 1.0, atol=1e-5)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_scene_up_is_the_axis_nearest_the_cameras_up_and_turns_to_y_up(seed):
    from tesseract4d.geometry import rotation_to_y_up, scene_up_axis

    T = random_pose(np.random.default_rng(seed))
    up = scene_up_axis(T)
    assert sorted(np.abs(up)) == [0.0, 0.0, 1.0]
    assert up @ -T[:3, 1] == np.max(np.abs(T[:3, 1]))  # the camera's up leans most on this axis, this way
    R = rotation_to_y_up(up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R @ up, [0.0, 1.0, 0.0], atol=1e-12)


def test_z_up_turns_to_y_up_keeping_x():
    from tesseract4d.geometry import rotation_to_y_up

    R = rotation_to_y_up(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)  # x stays
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], atol=1e-12)  # +y (away) to -z
