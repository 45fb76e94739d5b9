"""Camera conventions: GL->CV conversion properties, and real SAPIEN renders checked against the
simulator's ground truth (cube top height, table normals, depth-derived normals)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tesseract4d.conventions import (
    CV_FROM_GL, T_world_cam_from_cam2world_gl, T_world_cam_from_extrinsic_cv, depth_m_from_mm, normal_gl_to_cv,
)
from tesseract4d.geometry import depth_to_world_points, invert_pose, normals_from_depth, rotate_vectors

CUBE_HALF_SIZE_M = 0.02  # PickCube-v1's cube


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_gl_normals_converted_to_cv_map_back_to_the_same_world_normal(seed):
    rng = np.random.default_rng(seed)
    cam2world_gl = np.eye(4)
    cam2world_gl[:3, :3] = _random_rotation(rng)
    cam2world_gl[:3, 3] = rng.normal(size=3)
    n_world = rng.normal(size=(10, 3))
    n_world /= np.linalg.norm(n_world, axis=1, keepdims=True)
    n_gl = n_world @ cam2world_gl[:3, :3]  # world -> GL camera frame (R^T n)
    T_world_cam = T_world_cam_from_cam2world_gl(cam2world_gl)
    back = rotate_vectors(T_world_cam, normal_gl_to_cv(n_gl))
    np.testing.assert_allclose(back, n_world, atol=1e-5)
    # OpenCV axes: +z forward is GL's -z, +y down is GL's -y.
    np.testing.assert_allclose(T_world_cam[:3, 2], -cam2world_gl[:3, 2])
    np.testing.assert_allclose(T_world_cam[:3, 1], -cam2world_gl[:3, 1])
    np.testing.assert_allclose(CV_FROM_GL @ CV_FROM_GL, np.eye(3))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_extrinsic_and_cam2world_agree(seed):
    rng = np.random.default_rng(seed)
    cam2world_gl = np.eye(4)
    cam2world_gl[:3, :3] = _random_rotation(rng)
    cam2world_gl[:3, 3] = rng.normal(size=3)
    T = T_world_cam_from_cam2world_gl(cam2world_gl)
    extrinsic_cv = invert_pose(T)[:3]
    np.testing.assert_allclose(T_world_cam_from_extrinsic_cv(extrinsic_cv), T, atol=1e-9)


def test_depth_mm_to_m_keeps_no_hit_zero():
    d = depth_m_from_mm(np.array([[0, 1000, 40]], np.int16))
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [[0.0, 1.0, 0.04]])


def test_zero_normals_stay_zero():
    assert np.all(normal_gl_to_cv(np.zeros((2, 2, 3))) == 0)


# --------------------------------------------------------------------------- real renders


@pytest.fixture(scope="module")
def pickcube_first_frame():
    from datagen.simulate import render_first_frame

    return render_first_frame("PickCube-v1", 3, height=128, width=128, camera="all")


def _ids(cam, name):
    return [i for i, n in cam.seg_id_to_name.items() if n == name]


@pytest.mark.sim
@pytest.mark.parametrize("camera", ["base_camera", "close", "side"])
def test_back_projected_cube_top_is_within_3mm_of_the_true_pose(pickcube_first_frame, camera):
    ep = pickcube_first_frame
    cam = ep.cameras[camera]
    cube_pose = ep.object_poses["cube"][0]  # (7,) xyz + wxyz
    mask = np.isin(cam.segmentation[0], _ids(cam, "cube"))
    assert mask.sum() >= 4, f"{camera}: the cube covers only {mask.sum()} pixels"
    depth = np.where(mask, cam.depth_m[0], 0.0)
    points, valid = depth_to_world_points(depth, cam.K[0], cam.T_world_cam[0])
    normals_world = rotate_vectors(cam.T_world_cam[0], cam.normal_cam[0][valid])
    top = points[normals_world[:, 2] > 0.9]  # pixels on the cube's upward face
    assert len(top) >= 2, f"{camera}: no pixels of the cube's top face"
    true_top_z = cube_pose[2] + CUBE_HALF_SIZE_M
    assert abs(np.median(top[:, 2]) - true_top_z) < 0.003
    # Every cube pixel lies inside the cube (3 mm tolerance): x, y within the rotated footprint.
    offset = np.linalg.norm(points[:, :2] - cube_pose[:2], axis=1)
    assert offset.max() < CUBE_HALF_SIZE_M * np.sqrt(2) + 0.003


@pytest.mark.sim
@pytest.mark.parametrize("camera", ["base_camera", "close"])
def test_table_normals_point_up_in_world(pickcube_first_frame, camera):
    cam = pickcube_first_frame.cameras[camera]
    mask = np.isin(cam.segmentation[0], _ids(cam, "table-workspace"))
    assert mask.sum() > 100
    n_world = rotate_vectors(cam.T_world_cam[0], cam.normal_cam[0][mask])
    assert np.median(n_world[:, 2]) > 0.99
    assert np.mean(n_world[:, 2] > 0.95) > 0.95
    np.testing.assert_allclose(np.linalg.norm(n_world, axis=1), 1.0, atol=2e-3)  # float16 storage


@pytest.mark.sim
def test_rendered_normals_agree_with_normals_from_depth(pickcube_first_frame):
    cam = pickcube_first_frame.cameras["close"]
    from_depth = normals_from_depth(cam.depth_m[0], cam.K[0])
    mask = np.isin(cam.segmentation[0], _ids(cam, "table-workspace")) & np.any(from_depth != 0, axis=-1)
    cos = np.sum(from_depth[mask] * cam.normal_cam[0][mask], axis=-1)
    assert np.median(cos) > 0.98  # same frame and orientation (a GL/CV mix-up gives negative cosines)
