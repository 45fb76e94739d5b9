"""Observation -> the fixed-size world-frame point cloud the inverse dynamics model reads.

A frame's metric depth is back-projected with its intrinsics and camera pose (the project's one
back-projection, ``tesseract4d.geometry.depth_to_world_points``), cropped to the tabletop
workspace, and sampled to exactly ``num_points`` points of (x, y, z, r, g, b): world metres and
colour in [0, 1]. Predicted frames take the same path, so the model sees generated and
simulated frames alike (predicted depth 0 = beyond the model's depth range = dropped).
"""

from __future__ import annotations

import numpy as np

from tesseract4d.geometry import depth_to_world_points

# The workspace box in the world frame of the tabletop tasks (robot base at x = -0.615, table top
# z = 0, objects within about +-0.1 m of the origin): the arm, the objects and the table around them.
WORKSPACE_MIN_M = np.array([-0.75, -0.45, -0.02], np.float32)
WORKSPACE_MAX_M = np.array([0.35, 0.45, 0.80], np.float32)
POINT_CHANNELS = 6  # x, y, z (world metres), r, g, b (0..1)


def frame_points(rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                 num_points: int, rng: np.random.Generator) -> np.ndarray:
    """(num_points, 6) float32 world points with colour of one RGB-D frame (H, W, 3) / (H, W).

    Points are drawn without replacement from the workspace pixels (with replacement when there are
    fewer). A frame with no workspace pixel gives all-zero points (the model then sees nothing).
    """
    xyz, valid = depth_to_world_points(depth_m, K, T_world_cam)  # (N, 3), (H, W)
    colors = np.asarray(rgb)[valid].astype(np.float32) / 255.0  # (N, 3)
    inside = np.all((xyz >= WORKSPACE_MIN_M) & (xyz <= WORKSPACE_MAX_M), axis=1)
    xyz, colors = xyz[inside], colors[inside]
    out = np.zeros((num_points, POINT_CHANNELS), np.float32)
    if len(xyz) == 0:
        return out
    idx = rng.choice(len(xyz), size=num_points, replace=len(xyz) < num_points)
    out[:, :3], out[:, 3:] = xyz[idx], colors[idx]
    return out
