"""Optical flow between consecutive RGB frames (OpenCV DIS) and static / dynamic masks.

Flow convention: ``flow_prev[t]`` (H, W, 2) maps pixel p of frame t to where the same surface
point is in frame t-1: ``p + flow_prev[t][p]`` (pixels, u then v). ``flow_prev[0]`` is zero.

A pixel is dynamic when its flow differs from the flow the camera's own motion would cause
(zero for a static camera) by more than a threshold. Flow is unreliable inside uniformly
coloured regions (the aperture problem), so the moving mask is dilated and its enclosed holes
are filled: the inside of a moving object counts as moving too.
"""

from __future__ import annotations

import numpy as np

from tesseract4d.geometry import invert_pose, pixel_grid, project_points, transform_points, unproject_depth

# DIS underestimates motion on small frames (its coarsest patches cover whole objects);
# frames smaller than this are upsampled for the flow.
MIN_FLOW_SIZE = 256


def _gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(np.ascontiguousarray(rgb, np.uint8), cv2.COLOR_RGB2GRAY)


def dis_flow(frame_from: np.ndarray, frame_to: np.ndarray) -> np.ndarray:
    """Dense flow (H, W, 2) float32 from ``frame_from`` to ``frame_to`` ((H, W, 3) uint8):
    pixel p of ``frame_from`` shows what ``frame_to`` shows at p + flow[p]."""
    import cv2

    a, b = _gray(frame_from), _gray(frame_to)
    H, W = a.shape
    scale = max(1, int(np.ceil(MIN_FLOW_SIZE / min(H, W))))
    if scale > 1:
        a = cv2.resize(a, (W * scale, H * scale), interpolation=cv2.INTER_LINEAR)
        b = cv2.resize(b, (W * scale, H * scale), interpolation=cv2.INTER_LINEAR)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(a, b, None)
    if scale > 1:
        flow = cv2.resize(flow, (W, H), interpolation=cv2.INTER_AREA) / scale
    return flow.astype(np.float32)


def flows_to_previous(rgb: np.ndarray) -> np.ndarray:
    """(T, H, W, 2) flow of every frame to its predecessor; frame 0 gets zeros."""
    T, H, W = rgb.shape[:3]
    flow = np.zeros((T, H, W, 2), np.float32)
    for t in range(1, T):
        flow[t] = dis_flow(rgb[t], rgb[t - 1])
    return flow


def ego_flow(depth_m: np.ndarray, K_t: np.ndarray, T_world_cam_t: np.ndarray,
             K_prev: np.ndarray, T_world_cam_prev: np.ndarray) -> np.ndarray:
    """Flow (H, W, 2) from frame t to frame t-1 that a static scene would show, from frame t's
    depth and both cameras; zero where depth is missing."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    pts_t = unproject_depth(np.where(valid, depth_m, 0.0), K_t)
    T_prev_t = invert_pose(T_world_cam_prev) @ np.asarray(T_world_cam_t, np.float64)
    uv_prev, z_prev = project_points(transform_points(T_prev_t, pts_t), K_prev)
    u, v = pixel_grid(*depth_m.shape)
    flow = uv_prev - np.stack([u, v], -1)
    ok = valid & (z_prev > 0) & np.all(np.isfinite(flow), -1)
    return np.where(ok[..., None], flow, 0.0).astype(np.float32)


def camera_is_static(K: np.ndarray, T_world_cam: np.ndarray, tol: float = 1e-6) -> bool:
    return bool(np.allclose(T_world_cam, T_world_cam[:1], atol=tol) and np.allclose(K, K[:1], atol=tol))


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Mask (H, W) bool with every region enclosed by it (not reachable from the border) set."""
    import cv2

    H, W = mask.shape
    outside = np.zeros((H + 2, W + 2), np.uint8)
    outside[1:-1, 1:-1] = mask.astype(np.uint8)
    flood = outside.copy()
    cv2.floodFill(flood, None, (0, 0), 2)
    return mask | (flood[1:-1, 1:-1] == 0)


def motion_masks(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    threshold_px: float,
    dilate_px: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow to the previous frame and the dynamic mask of every frame.

    rgb (T, H, W, 3) uint8, depth_m (T, H, W), K (T, 3, 3), T_world_cam (T, 4, 4).
    Returns (flow_prev (T, H, W, 2) float32, dynamic (T, H, W) bool). Frame 0 has no
    predecessor; its mask comes from the flow to frame 1.
    """
    import cv2

    T, H, W = depth_m.shape
    flow_prev = flows_to_previous(rgb)
    static_cam = camera_is_static(K, T_world_cam)
    dynamic = np.zeros((T, H, W), bool)
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)

    def mask_of(flow, t_from, t_to):
        residual = flow if static_cam else flow - ego_flow(depth_m[t_from], K[t_from], T_world_cam[t_from], K[t_to], T_world_cam[t_to])
        moving = np.linalg.norm(residual, axis=-1) > threshold_px
        if dilate_px > 0:
            moving = cv2.dilate(moving.astype(np.uint8), kernel) > 0
        return fill_holes(moving)

    for t in range(1, T):
        dynamic[t] = mask_of(flow_prev[t], t, t - 1)
    if T > 1:
        dynamic[0] = mask_of(dis_flow(rgb[0], rgb[1]), 0, 1)
    return flow_prev, dynamic
