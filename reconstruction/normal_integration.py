"""Normal integration in log-depth for perspective cameras (the constraints of BiNI,
Cao et al. 2022), solved as sparse weighted least squares.

A surface seen by a pinhole camera is ``P(u, v) = z(u, v) * r(u, v)`` with the ray
``r = ((u - cx) / fx, (v - cy) / fy, 1)``. A normal ``n`` is orthogonal to both tangents
``dP/du`` and ``dP/dv``, which gives the log-depth gradients as functions of the normal alone::

    d log z / du = -n_x / (fx * (n . r)),      d log z / dv = -n_y / (fy * (n . r))

so the constraints are linear in the unknown ``log z``. Each pair of neighbouring pixels adds
one row ``log z_b - log z_a = mean of the two pixels' gradients``; a regulariser ties every
pixel to a reference depth (which also fixes the unknown scale). Rows across depth
discontinuities (where the reference depth jumps unlike the normals say, or the normals
disagree) are dropped, so separate surfaces are not glued together.

:class:`LeastSquares` collects such rows (also the temporal rows of ``consistency.py``) and
solves them with preconditioned conjugate gradients on the normal equations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tesseract4d.geometry import MIN_NORMAL_LENGTH, pixel_grid

# Pixels whose ray meets the surface this close to grazing give unbounded gradients; no rows.
MIN_RAY_COSINE = 0.05
# Rows whose target log-depth change exceeds this per pixel (a 20 % depth change) sit on a
# silhouette or a near-grazing surface, where the normal says little about the depth.
MAX_LOG_STEP = 0.2
# Outlier threshold of the gates, in robust standard deviations.
GATE_SIGMAS = 3.0


@dataclass
class LeastSquares:
    """Weighted sparse least squares ``min sum_i w_i (sum_k a_ik x_{c_ik} - b_i)^2``.

    Rows are added in blocks of equal width: ``cols`` (m, k) int, ``coeffs`` (m, k),
    ``rhs`` (m,), ``weight`` (m,) or a scalar.
    """

    num_unknowns: int
    _rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    def add(self, cols: np.ndarray, coeffs: np.ndarray, rhs: np.ndarray, weight: np.ndarray | float) -> None:
        cols = np.asarray(cols, np.int64)
        if cols.ndim == 1:
            cols = cols[:, None]
        coeffs = np.asarray(coeffs, np.float64)
        coeffs = np.broadcast_to(coeffs.reshape(len(cols), -1) if coeffs.size > 1 else coeffs, cols.shape)
        rhs = np.asarray(rhs, np.float64).reshape(len(cols))
        weight = np.broadcast_to(np.asarray(weight, np.float64), rhs.shape)
        keep = weight > 0
        if keep.any():
            self._rows.append((cols[keep], coeffs[keep], rhs[keep], weight[keep]))

    @property
    def num_rows(self) -> int:
        return sum(len(r[2]) for r in self._rows)

    def normal_equations(self):
        """(A^T W A as CSR, A^T W b)."""
        import scipy.sparse as sp

        n = self.num_unknowns
        if not self._rows:
            return sp.csr_matrix((n, n)), np.zeros(n)
        row_ids, col_ids, vals, rhs, weight = [], [], [], [], []
        start = 0
        for cols, coeffs, b, w in self._rows:
            m, k = cols.shape
            row_ids.append(np.repeat(np.arange(start, start + m), k))
            col_ids.append(cols.ravel())
            vals.append(coeffs.ravel())
            rhs.append(b)
            weight.append(w)
            start += m
        A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(row_ids), np.concatenate(col_ids))), shape=(start, n))
        w = np.concatenate(weight)
        AtW = A.T.multiply(w).tocsr()
        return (AtW @ A).tocsr(), AtW @ np.concatenate(rhs)

    def solve(self, x0: np.ndarray, iterations: int = 300, tolerance: float = 1e-5) -> tuple[np.ndarray, dict]:
        """Jacobi-preconditioned conjugate gradients from ``x0``; returns (x, info)."""
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        N, b = self.normal_equations()
        diag = N.diagonal()
        # Unknowns no row touches keep their start value (a unit diagonal with rhs = x0).
        free = diag <= 0
        if free.any():
            N = N + sp.diags(free.astype(np.float64))
            b = np.where(free, x0, b)
            diag = np.where(free, 1.0, diag)
        M = sp.diags(1.0 / diag)
        count = [0]

        def step(_):
            count[0] += 1

        x, status = spla.cg(N, b, x0=np.asarray(x0, np.float64), rtol=tolerance, maxiter=iterations, M=M, callback=step)
        residual = float(np.linalg.norm(N @ x - b) / max(np.linalg.norm(b), 1e-30))
        return x, {"iterations": count[0], "converged": status == 0, "relative_residual": residual, "rows": self.num_rows}


def log_depth_gradients(normal_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel log-depth gradients implied by normals (perspective camera).

    normal_cam: (H, W, 3) OpenCV camera frame (any length; zero = none). K: (3, 3).
    Returns (d log z / du (H, W), d log z / dv (H, W), usable (H, W) bool): usable where the
    normal exists and its ray is not near grazing.
    """
    n = np.asarray(normal_cam, np.float64)
    K = np.asarray(K, np.float64)
    H, W = n.shape[:2]
    u, v = pixel_grid(H, W)
    length = np.linalg.norm(n, axis=-1)
    n = n / np.maximum(length, 1e-12)[..., None]
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    n_dot_r = (n * ray).sum(-1)
    cosine = np.abs(n_dot_r) / np.linalg.norm(ray, axis=-1)
    usable = (length > MIN_NORMAL_LENGTH) & np.isfinite(length) & (cosine > MIN_RAY_COSINE)
    safe = np.where(usable, n_dot_r, 1.0)
    gu = np.where(usable, -n[..., 0] / (K[0, 0] * safe), 0.0)
    gv = np.where(usable, -n[..., 1] / (K[1, 1] * safe), 0.0)
    return gu, gv, usable


def add_normal_rows(
    problem: LeastSquares,
    index: np.ndarray,
    normal_cam: np.ndarray,
    K: np.ndarray,
    weight: float,
    log_depth_ref: np.ndarray | None = None,
    discontinuity_log_tol: float | None = None,
    discontinuity_normal_deg: float | None = None,
) -> int:
    """Add one row per pair of 4-neighbours: ``x_b - x_a = (g_a + g_b) / 2``.

    index: (H, W) int, the unknown of each pixel (-1 = none); unknowns are log depths.
    log_depth_ref: (H, W) log depth used to detect discontinuities: rows whose reference step
    differs from the normal-implied step by more than ``discontinuity_log_tol`` (or, for noisy
    references, GATE_SIGMAS robust standard deviations of those differences) are dropped.
    Returns the number of rows added.
    """
    gu, gv, usable = log_depth_gradients(normal_cam, K)
    n = np.asarray(normal_cam, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    candidates = []
    for axis, g in ((1, gu), (0, gv)):
        a = (slice(None), slice(0, -1)) if axis == 1 else (slice(0, -1), slice(None))
        b = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        ia, ib = index[a], index[b]
        target = 0.5 * (g[a] + g[b])
        ok = (ia >= 0) & (ib >= 0) & usable[a] & usable[b] & (np.abs(target) < MAX_LOG_STEP)
        if discontinuity_normal_deg is not None:
            ok &= (n[a] * n[b]).sum(-1) > np.cos(np.deg2rad(discontinuity_normal_deg))
        residual = (log_depth_ref[b] - log_depth_ref[a] - target)[ok] if log_depth_ref is not None else None
        candidates.append((ia[ok], ib[ok], target[ok], residual))
    keep = [np.ones(len(c[2]), bool) for c in candidates]
    if log_depth_ref is not None and discontinuity_log_tol is not None:
        # Noisy reference depth spreads the residuals of smooth surfaces: the threshold is at
        # least GATE_SIGMAS robust standard deviations (1.4826 MAD) of the frame's residuals.
        residuals = np.concatenate([c[3] for c in candidates])
        spread = 1.4826 * float(np.median(np.abs(residuals))) if len(residuals) else 0.0
        tol = max(discontinuity_log_tol, GATE_SIGMAS * spread)
        keep = [np.abs(c[3]) < tol for c in candidates]
    added = 0
    for (ia, ib, target, _), k in zip(candidates, keep):
        m = int(k.sum())
        if m:
            problem.add(np.stack([ia[k], ib[k]], -1), np.tile([-1.0, 1.0], (m, 1)), target[k], weight)
        added += m
    return added


def integrate_normals(
    normal_cam: np.ndarray,
    K: np.ndarray,
    depth_ref_m: np.ndarray,
    mask: np.ndarray | None = None,
    normal_weight: float = 100.0,
    reg_weight: float = 2.0,
    discontinuity_log_tol: float | None = None,
    discontinuity_normal_deg: float | None = None,
    iterations: int = 500,
    tolerance: float = 1e-6,
) -> np.ndarray:
    """Depth (H, W) float32 that agrees with the normals and stays near ``depth_ref_m``.

    normal_cam: (H, W, 3) OpenCV camera frame. depth_ref_m: (H, W) metres, > 0 where
    known; its pixels (within ``mask``) are the ones solved for, the rest stay 0.
    ``reg_weight`` ties each pixel's log depth to the reference; relative to ``normal_weight``
    it sets how far (about sqrt(normal_weight / reg_weight) pixels) normals smooth the depth.
    """
    depth = np.asarray(depth_ref_m, np.float64)
    if depth.shape != np.asarray(normal_cam).shape[:2]:
        raise ValueError(f"depth {depth.shape} and normals {np.asarray(normal_cam).shape} differ in size")
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= np.asarray(mask, bool)
    out = np.zeros(depth.shape, np.float32)
    if not valid.any():
        return out
    index = np.full(depth.shape, -1, np.int64)
    index[valid] = np.arange(valid.sum())
    log_ref = np.log(np.where(valid, depth, 1.0))
    problem = LeastSquares(int(valid.sum()))
    add_normal_rows(problem, index, normal_cam, K, normal_weight, log_ref, discontinuity_log_tol, discontinuity_normal_deg)
    problem.add(index[valid], 1.0, log_ref[valid], reg_weight)
    x, _ = problem.solve(log_ref[valid], iterations=iterations, tolerance=tolerance)
    out[valid] = np.exp(x)
    return out
