"""Temporal consistency rows: tie each frame's log depth to the previous frame's, warped along
the optical flow (and through the camera motion, if any).

For pixel p of frame t with flow target q = p + flow_prev[t][p] in frame t-1, the row is::

    x_t(p) - bilinear(x_{t-1}, q) = c(p)

where x are log depths and c is the log-depth change the camera motion alone causes (zero for a
static camera). Rows whose pixel is static in both frames get the background weight, the others
the dynamic weight. A row is dropped when the reference depths disagree by more than a gate
(occlusions and disocclusions, where the flow points at a different surface) or when q's four
neighbours are not all valid.
"""

from __future__ import annotations

import numpy as np

from reconstruction.normal_integration import GATE_SIGMAS, LeastSquares
from tesseract4d.geometry import invert_pose, pixel_grid


def _bilinear(img: np.ndarray, y0: np.ndarray, x0: np.ndarray, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
    return ((1 - fy) * (1 - fx) * img[y0, x0] + (1 - fy) * fx * img[y0, x0 + 1]
            + fy * (1 - fx) * img[y0 + 1, x0] + fy * fx * img[y0 + 1, x0 + 1])


def add_temporal_rows(
    problem: LeastSquares,
    index: np.ndarray,
    log_depth_ref: np.ndarray,
    flow_prev: np.ndarray,
    dynamic: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    static_weight: float,
    dynamic_weight: float,
    gate_log: float,
) -> dict[str, int]:
    """Add the rows linking frames t and t-1 for t = 1..T-1.

    index (T, H, W) int unknown per pixel (-1 = none); log_depth_ref (T, H, W) reference log
    depth (for the gate and the camera-motion term); flow_prev (T, H, W, 2); dynamic (T, H, W)
    bool; K (T, 3, 3); T_world_cam (T, 4, 4). Returns row counts {"static": n, "dynamic": m}.
    """
    T, H, W = index.shape
    u, v = pixel_grid(H, W)
    counts = {"static": 0, "dynamic": 0}
    for t in range(1, T):
        here = index[t] >= 0
        # Continuous array coordinates of q (pixel centres sit at integer + 0.5).
        x = u + flow_prev[t][..., 0] - 0.5
        y = v + flow_prev[t][..., 1] - 0.5
        inside = here & (x >= 0) & (y >= 0) & (x < W - 1) & (y < H - 1)
        rows, cols = np.nonzero(inside)
        xq, yq = x[rows, cols], y[rows, cols]
        x0, y0 = np.floor(xq).astype(np.int64), np.floor(yq).astype(np.int64)
        fx, fy = xq - x0, yq - y0
        prev = index[t - 1]
        corners = np.stack([prev[y0, x0], prev[y0, x0 + 1], prev[y0 + 1, x0], prev[y0 + 1, x0 + 1]], -1)
        weights = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
        ok = np.all(corners >= 0, -1)
        ref_prev = _bilinear(log_depth_ref[t - 1], y0, x0, fy, fx)
        offset = np.zeros(len(rows))
        T_t_prev = invert_pose(T_world_cam[t]) @ np.asarray(T_world_cam[t - 1], np.float64)
        if not np.allclose(T_t_prev, np.eye(4), atol=1e-9):
            # A point at depth z on q's ray has depth z * (R r)_z + t_z in frame t.
            Kp = K[t - 1]
            ray = np.stack([(xq + 0.5 - Kp[0, 2]) / Kp[0, 0], (yq + 0.5 - Kp[1, 2]) / Kp[1, 1], np.ones_like(xq)], -1)
            a = ray @ T_t_prev[2, :3]
            ratio = a + T_t_prev[2, 3] / np.exp(ref_prev)
            ok &= ratio > 1e-6
            offset = np.log(np.where(ratio > 1e-6, ratio, 1.0))
        moving = dynamic[t][rows, cols] | dynamic[t - 1][np.rint(yq).astype(np.int64), np.rint(xq).astype(np.int64)]
        change = log_depth_ref[t][rows, cols] - ref_prev - offset
        # A global depth-scale flicker between the frames is what these rows should remove,
        # not a sign of occlusion: gate on the change relative to the frame's median change.
        typical = ok & ~moving if (ok & ~moving).any() else ok
        flicker = float(np.median(change[typical])) if typical.any() else 0.0
        # Noisy depth spreads the changes of true matches; keep those within GATE_SIGMAS robust
        # standard deviations (1.4826 MAD), and at least within gate_log.
        spread = 1.4826 * float(np.median(np.abs(change[typical] - flicker))) if typical.any() else 0.0
        ok &= np.abs(change - flicker) < max(gate_log, GATE_SIGMAS * spread)
        for label, sel, weight in (("static", ok & ~moving, static_weight), ("dynamic", ok & moving, dynamic_weight)):
            m = int(sel.sum())
            if m and weight > 0:
                cols_ = np.concatenate([index[t][rows[sel], cols[sel]][:, None], corners[sel]], -1)
                coeffs = np.concatenate([np.ones((m, 1)), -weights[sel]], -1)
                problem.add(cols_, coeffs, offset[sel], weight)
            counts[label] += m
    return counts
