"""Pure camera geometry (numpy, no I/O). OpenCV camera axes everywhere; see conventions.py.

Shapes: images are (H, W[, C]); ``K`` is (3, 3); poses ``T_a_b`` are (4, 4) and map points
in frame b to frame a. Depth is metric z-depth (``depth_m``), 0 = no measurement.
"""

from __future__ import annotations

import numpy as np

# A stored normal counts as measured when it is longer than this: normals are unit vectors or
# zero ("no measurement"), and float16 storage keeps unit ones within 1e-3 of length 1.
MIN_NORMAL_LENGTH = 0.5


def invert_pose(T_a_b: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (…, 4, 4): returns T_b_a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) rigid transform to points (…, 3) in frame b; returns points in frame a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(points_b)
    return (p @ T[:3, :3].T + T[:3, 3]).astype(np.result_type(p.dtype, np.float32))


def rotate_vectors(T_a_b: np.ndarray, vectors_b: np.ndarray) -> np.ndarray:
    """Rotate direction vectors (…, 3), e.g. normals, from frame b to frame a (no translation)."""
    R = np.asarray(T_a_b, dtype=np.float64)[:3, :3]
    v = np.asarray(vectors_b)
    return (v @ R.T).astype(np.result_type(v.dtype, np.float32))


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (u, v), each (H, W) float64, u along width, v along height.

    Pixel (row i, col j) has its centre at u = j + 0.5, v = i + 0.5 (the OpenCV/SAPIEN
    convention where K's principal point of W/2 is the image centre).
    """
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return u, v


def unproject_depth(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project a depth map (H, W) to camera-frame points (H, W, 3), float32.

    Pixels with depth 0 map to the origin; mask them with ``depth_m > 0``.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    u, v = pixel_grid(*depth.shape)
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    return np.stack([x, y, depth], axis=-1).astype(np.float32)


def project_points(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points (…, 3) to pixel coordinates.

    Returns (uv (…, 2) in the pixel-centre convention of ``pixel_grid``, z (…) depth in metres).
    """
    p = np.asarray(points_cam, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[..., 0] / z + K[0, 2]
        v = K[1, 1] * p[..., 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1), z


def depth_to_world_points(
    depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a depth map as world points.

    Returns (points_world (N, 3) float32, valid (H, W) bool) where N = valid.sum().
    """
    valid = np.isfinite(depth_m) & (np.asarray(depth_m) > 0)
    points_cam = unproject_depth(np.where(valid, depth_m, 0.0), K)[valid]
    return transform_points(T_world_cam, points_cam), valid


def normals_from_depth(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Surface normals (H, W, 3) in the camera frame from a depth map, by central differences.

    Normals are unit length, oriented toward the camera (n · p < 0). Pixels without valid
    depth, or whose neighbours lack it, get the zero vector.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    P = unproject_depth(np.where(valid, depth, 0.0), K).astype(np.float64)
    # Central differences where both neighbours are valid, one-sided otherwise.
    def diff(axis: int) -> tuple[np.ndarray, np.ndarray]:
        fwd = np.roll(P, -1, axis=axis) - P
        bwd = P - np.roll(P, 1, axis=axis)
        vf = valid & np.roll(valid, -1, axis=axis)
        vb = valid & np.roll(valid, 1, axis=axis)
        n = P.shape[axis]
        edge = np.zeros(valid.shape, dtype=bool)
        idx_last = [slice(None)] * 2
        idx_last[axis] = n - 1
        edge[tuple(idx_last)] = True
        vf &= ~edge
        idx_first = [slice(None)] * 2
        idx_first[axis] = 0
        edge0 = np.zeros(valid.shape, dtype=bool)
        edge0[tuple(idx_first)] = True
        vb &= ~edge0
        d = np.where((vf & vb)[..., None], 0.5 * (fwd + bwd), np.where(vf[..., None], fwd, bwd))
        return d, vf | vb

    du, ok_u = diff(1)
    dv, ok_v = diff(0)
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = valid & ok_u & ok_v & (norm[..., 0] > 1e-12)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12), 0.0)
    flip = (n * P).sum(-1) > 0
    n[flip] *= -1
    return n.astype(np.float32)


def scene_up_axis(T_world_cam: np.ndarray) -> np.ndarray:
    """The signed world axis closest to a camera's up direction (its -y: OpenCV y points down),
    e.g. +z in ManiSkill's world. ``T_world_cam``: (4, 4). Returns a (3,) unit axis vector."""
    up = -np.asarray(T_world_cam, np.float64)[:3, 1]
    axis = int(np.argmax(np.abs(up)))
    unit = np.zeros(3)
    unit[axis] = 1.0 if up[axis] >= 0 else -1.0
    return unit


def rotation_to_y_up(up_axis: np.ndarray) -> np.ndarray:
    """The (3, 3) rotation that turns the signed world axis ``up_axis`` into +y (glTF's up), by a
    quarter turn about the axis they both lie across (a half turn about x when it is -y)."""
    u = np.asarray(up_axis, np.float64)
    y = np.array([0.0, 1.0, 0.0])
    if np.allclose(u, y):
        return np.eye(3)
    if np.allclose(u, -y):
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(u, y)  # unit: u and y are orthogonal unit axes
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K  # Rodrigues at 90 degrees
