"""Normal integration recovers known surfaces from exact normals (up to the global scale that
normals cannot see), within stated tolerances."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.normal_integration import integrate_normals, log_depth_gradients
from tesseract4d.geometry import normals_from_depth, pixel_grid

H = W = 48
K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
# Median relative depth error after the best scale, and the worst one.
MEDIAN_TOL, MAX_TOL = 1e-3, 5e-3


def rays() -> np.ndarray:
    u, v = pixel_grid(H, W)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


def sphere(center=(0.05, -0.03, 1.0), radius=0.35):
    r, c = rays(), np.asarray(center)
    a, b, cc = (r**2).sum(-1), -2 * (r @ c), c @ c - radius**2
    disc = b * b - 4 * a * cc
    hit = disc > 0
    z = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a), 0.0)
    n = np.where(hit[..., None], (r * z[..., None] - c) / radius, 0.0)
    # Keep pixels whose ray meets the sphere at least 20 degrees off grazing.
    facing = -(n * r).sum(-1) / np.linalg.norm(r, axis=-1)
    return z, n, hit & (facing > np.sin(np.deg2rad(20)))


def slanted_plane(normal=(0.3, -0.4, -1.0), d=0.8):
    n = np.asarray(normal) / np.linalg.norm(normal)
    z = -d / (rays() @ n)
    return z, np.broadcast_to(n, (H, W, 3)).copy(), np.ones((H, W), bool)


def scale_aligned_errors(depth, truth, mask):
    scale = np.exp(np.mean(np.log(truth[mask]) - np.log(depth[mask])))
    rel = np.abs(depth[mask] * scale / truth[mask] - 1)
    return np.median(rel), rel.max()


@pytest.mark.parametrize("surface", [sphere, slanted_plane], ids=["sphere", "slanted_plane"])
def test_recovers_surface_from_exact_normals(surface):
    truth, normals, mask = surface()
    flat_start = np.where(mask, 0.7, 0.0)  # a wrong, flat initial depth
    depth = integrate_normals(normals, K, flat_start, normal_weight=1.0, reg_weight=1e-5)
    median, worst = scale_aligned_errors(depth, truth, mask)
    print(f"{surface.__name__}: median rel error {median:.2e}, max {worst:.2e}")
    assert median < MEDIAN_TOL and worst < MAX_TOL
    assert np.all(depth[~mask] == 0)


def test_gradients_match_finite_differences_of_log_depth():
    truth, normals, mask = sphere()
    gu, gv, usable = log_depth_gradients(normals, K)
    inner = mask[:, 1:-1] & mask[:, 2:] & mask[:, :-2]
    fd = 0.5 * (np.log(np.maximum(truth[:, 2:], 1e-9)) - np.log(np.maximum(truth[:, :-2], 1e-9)))
    np.testing.assert_allclose(gu[:, 1:-1][inner], fd[inner], atol=2e-3)
    assert usable[mask].all() and not usable[~mask & (truth == 0)].any()


def test_noisy_depth_is_smoothed_toward_the_normals():
    truth, normals, mask = slanted_plane()
    noisy = truth * (1 + 0.02 * np.random.default_rng(0).standard_normal(truth.shape))
    depth = integrate_normals(normals, K, noisy)
    err_in = np.abs(noisy / truth - 1).mean()
    err_out = np.abs(depth / truth - 1).mean()
    print(f"plane, 2% noise: mean rel error {err_in:.4f} -> {err_out:.4f}")
    assert err_out < 0.25 * err_in
    # The refined normals agree with the given ones.
    n_out = normals_from_depth(depth, K)[2:-2, 2:-2].reshape(-1, 3)
    assert np.degrees(np.arccos(np.clip(n_out @ normals[0, 0], -1, 1))).mean() < 1.0


def test_discontinuity_is_kept():
    # Two fronto-parallel planes at 1.0 m and 1.5 m, side by side: a depth step normals cannot see.
    truth = np.where(pixel_grid(H, W)[0] < W / 2, 1.0, 1.5)
    normals = np.broadcast_to([0.0, 0.0, -1.0], (H, W, 3)).copy()
    depth = integrate_normals(normals, K, truth, discontinuity_log_tol=0.05)
    np.testing.assert_allclose(depth, truth, rtol=1e-4)
