"""Camera conventions: the one place where SAPIEN/OpenGL and OpenCV camera frames meet.

Everything in tesseract4d uses OpenCV camera axes (x right, y down, z forward).
SAPIEN/ManiSkill report some quantities in the OpenGL camera frame (x right, y up,
z backward): the ``default`` shader's normals and ``cam2world_gl``. Convert them here, once,
at capture time; no other module flips axes.

Names carry frame and unit: ``depth_m`` (metres along +z_cv, 0 = no measurement),
``K`` (3x3 pixel intrinsics), ``T_world_cam`` (4x4, maps camera-frame points to world),
``normal_cam`` (unit vectors in the OpenCV camera frame, pointing toward the camera side).
"""

from __future__ import annotations

import numpy as np

from tesseract4d.geometry import invert_pose

# Maps OpenCV camera coordinates to OpenGL camera coordinates (and back: it is its own inverse).
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
CV_FROM_GL = GL_FROM_CV

# ManiSkill's "default" shader pack gives depth as int16 millimetres.
DEPTH_UNIT_MM_TO_M = 1e-3


def normal_gl_to_cv(normal_gl: np.ndarray) -> np.ndarray:
    """Rotate normals from the OpenGL camera frame to the OpenCV camera frame.

    normal_gl: (..., 3). Returns (..., 3) float32; zero vectors (no hit) stay zero.
    """
    n = np.asarray(normal_gl, dtype=np.float32)
    return n * np.array([1.0, -1.0, -1.0], dtype=np.float32)


def T_world_cam_from_cam2world_gl(cam2world_gl: np.ndarray) -> np.ndarray:
    """(…, 4, 4) OpenGL camera→world pose to the OpenCV camera→world pose ``T_world_cam``."""
    T = np.array(cam2world_gl, dtype=np.float64, copy=True)
    T[..., :3, :3] = T[..., :3, :3] @ CV_FROM_GL
    return T


def T_world_cam_from_extrinsic_cv(extrinsic_cv: np.ndarray) -> np.ndarray:
    """(…, 3|4, 4) world→camera OpenCV extrinsic to the camera→world pose ``T_world_cam``."""
    E = np.asarray(extrinsic_cv, dtype=np.float64)
    T_cam_world = np.zeros(E.shape[:-2] + (4, 4))
    T_cam_world[..., :3, :] = E[..., :3, :]
    T_cam_world[..., 3, 3] = 1.0

    return invert_pose(T_cam_world)


def depth_m_from_mm(depth_mm: np.ndarray) -> np.ndarray:
    """Integer millimetre depth (0 = no hit) to float32 metres (0 = no hit)."""
    return np.asarray(depth_mm, dtype=np.float32) * np.float32(DEPTH_UNIT_MM_TO_M)
