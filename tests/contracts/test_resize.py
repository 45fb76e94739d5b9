"""Property tests of resizing an RGB-D-N frame and its K (tesseract4d/resize.py)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from tesseract4d.errors import UserError
from tesseract4d.geometry import pixel_grid, unproject_depth
from tesseract4d.resize import resize_factor, resize_rgbdn, scale_intrinsics

SIZES = st.sampled_from([4, 6, 8, 12])
FACTORS = st.sampled_from([2, 3, 4])


def camera(h: int, w: int) -> np.ndarray:
    return np.array([[1.1 * w, 0.0, w / 2], [0.0, 1.0 * w, h / 2], [0.0, 0.0, 1.0]])


def plane_frame(h: int, w: int, tilt_deg: float, azimuth_deg: float, distance_m: float):
    """A plane m·p = -c seen by camera(h, w): (rgb, depth_m, normal_cam, K, m, c). m faces the camera.
    Pixels whose ray misses the plane (above its horizon) have no measurement: depth 0, normal 0."""
    a, b = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
    m = np.array([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), -np.cos(a)])
    K = camera(h, w)
    with np.errstate(divide="ignore"):
        plane, rays = plane_depth(m, distance_m, K, *pixel_grid(h, w))
    hit = rays @ m < 0
    depth = np.where(hit, plane, 0.0)
    rgb = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    normal = np.where(hit[..., None], m, 0.0).astype(np.float32)
    return rgb, depth.astype(np.float32), normal, K, m, distance_m


def plane_depth(m, c, K, u, v):
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return -c / (rays @ m), rays


def test_resize_factor_is_a_whole_number_or_its_inverse_on_both_axes():
    assert resize_factor((64, 64), (128, 128)) == 2
    assert resize_factor((128, 96), (32, 24)) == Fraction(1, 4)
    assert resize_factor((64, 64), (64, 64)) == 1
    assert resize_factor((64, 64), (96, 96)) is None  # 3/2
    assert resize_factor((64, 64), (128, 64)) is None  # differs per axis
    assert resize_factor((64, 64), (0, 0)) is None
    with pytest.raises(UserError, match="whole factor"):
        resize_rgbdn(*plane_frame(8, 8, 0, 0, 1.0)[:4], 12, 12)


@settings(max_examples=20, deadline=None)
@given(h=SIZES, w=SIZES, seed=st.integers(0, 2**16))
def test_resizing_to_the_same_size_is_identity(h, w, seed):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0, 2, (2, h, w)).astype(np.float32)
    normal = rng.standard_normal((2, h, w, 3)).astype(np.float32)
    K = np.repeat(camera(h, w)[None], 2, 0)
    out = resize_rgbdn(rgb, depth, normal, K, h, w)
    for a, b in zip(out, (rgb, depth, normal, K)):
        assert a.dtype == b.dtype and np.array_equal(a, b)


@settings(max_examples=30, deadline=None)
@given(h=SIZES, w=SIZES, k=FACTORS, up=st.booleans(), distance=st.floats(0.2, 3.0))
def test_a_fronto_parallel_plane_keeps_its_depth_and_normal(h, w, k, up, distance):
    rgb, depth, normal, K, _, _ = plane_frame(h * k, w * k, 0.0, 0.0, distance)
    if up:
        rgb, depth, normal, K = resize_rgbdn(rgb, depth, normal, K, h, w)
    H, W = (h * k * k, w * k * k) if up else (h, w)
    rgb2, depth2, normal2, K2 = resize_rgbdn(rgb, depth, normal, K, H, W)
    assert depth2.shape == (H, W) and rgb2.shape == (H, W, 3) and normal2.shape == (H, W, 3)
    np.testing.assert_allclose(depth2, np.float32(distance), rtol=1e-6)
    np.testing.assert_allclose(normal2, np.broadcast_to([0, 0, -1], normal2.shape), atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(h=SIZES, w=SIZES, k=FACTORS, up=st.booleans(), tilt=st.floats(0.0, 45.0), azimuth=st.floats(0.0, 360.0),
       distance=st.floats(0.2, 3.0))
@example(h=12, w=4, k=2, up=True, tilt=33.0, azimuth=250.0, distance=1.0)  # a footprint across the horizon
def test_points_of_a_resized_plane_stay_on_it_within_a_pixel_footprint(h, w, k, up, tilt, azimuth, distance):
    """Every back-projected point of the resized frame lies on its pixel's ray between the plane's
    nearest and farthest points over the footprint of one pixel of the coarser image around it.

    A tall frame of this camera sees up to 56° above its axis, so a tilted plane's horizon can cross
    the image: a footprint with a corner whose ray misses the plane (depth <= 0) reaches infinitely far
    along it and bounds nothing, so those pixels are left out (the others must still hold). Pixels
    without a measurement come out without one (depth 0, normal 0); every other normal is the plane's."""
    src = (h, w) if up else (h * k, w * k)
    dst = (h * k, w * k) if up else (h, w)
    rgb, depth, normal, K, m, c = plane_frame(*src, tilt, azimuth, distance)
    _, depth2, normal2, K2 = resize_rgbdn(rgb, depth, normal, K, *dst)
    side = k if up else 1  # the coarse pixel, in output pixels
    u, v = pixel_grid(*dst)
    corners = np.stack([plane_depth(m, c, K2, u + du * side / 2, v + dv * side / 2)[0]
                        for du in (-1, 1) for dv in (-1, 1)])
    bounded = (corners > 0).all(0)  # the footprint lies wholly below the plane's horizon
    assert bounded.any()
    lo, hi = corners.min(0)[bounded], corners.max(0)[bounded]
    d = depth2[bounded]
    assert (d >= lo * (1 - 1e-5)).all() and (d <= hi * (1 + 1e-5)).all()
    points = unproject_depth(depth2, K2).astype(np.float64)[bounded]
    _, rays = plane_depth(m, c, K2, u, v)
    off_plane = np.abs(points @ m + c)
    assert (off_plane <= (hi - lo) * np.abs(rays[bounded] @ m) + 1e-5).all()
    valid = depth2 > 0
    assert valid[bounded].all()
    np.testing.assert_allclose(normal2[valid], np.broadcast_to(m, normal2[valid].shape), atol=1e-5)
    assert not normal2[~valid].any()


@settings(max_examples=40, deadline=None)
@given(h=SIZES, w=SIZES, k=FACTORS, up=st.booleans(), seed=st.integers(0, 2**16))
def test_no_depth_falls_between_a_foreground_and_its_background(h, w, k, up, seed):
    """A box at 0.5 m in front of a wall at 1 m with a hole (no measurement): every resized depth is
    one of 0.5, 1 or 0, and every normal is unit or zero."""
    rng = np.random.default_rng(seed)
    H, W = (h, w) if up else (h * k, w * k)
    depth = np.ones((3, H, W), np.float32)
    normal = np.zeros((3, H, W, 3), np.float32)
    normal[..., 2] = -1
    for t in range(3):
        r0, c0 = rng.integers(0, H), rng.integers(0, W)
        depth[t, r0:r0 + rng.integers(1, H), c0:c0 + rng.integers(1, W)] = 0.5
        normal[t, r0:r0 + 2, c0:c0 + 2] = _unit(rng.standard_normal(3))  # a crease
        r1, c1 = rng.integers(0, H), rng.integers(0, W)
        depth[t, r1:r1 + 2, c1:c1 + 2], normal[t, r1:r1 + 2, c1:c1 + 2] = 0.0, 0.0
    rgb = rng.integers(0, 256, (3, H, W, 3), dtype=np.uint8)
    K = np.repeat(camera(H, W)[None], 3, 0)
    dst = (H * k, W * k) if up else (h, w)
    _, depth2, normal2, _ = resize_rgbdn(rgb, depth, normal, K, *dst)
    assert set(np.unique(depth2)) <= {np.float32(0), np.float32(0.5), np.float32(1)}
    length = np.linalg.norm(normal2, axis=-1)
    assert np.all((np.abs(length - 1) < 1e-5) | (length == 0))


def _unit(v):
    return v / np.linalg.norm(v)


@settings(max_examples=20, deadline=None)
@given(h=SIZES, w=SIZES, k=FACTORS, seed=st.integers(0, 2**16))
def test_normals_come_out_unit_or_zero(h, w, k, seed):
    rng = np.random.default_rng(seed)
    normal = rng.standard_normal((h * k, w * k, 3)).astype(np.float32)
    normal[rng.random((h * k, w * k)) < 0.2] = 0.0
    normal = np.where(np.linalg.norm(normal, axis=-1, keepdims=True) > 0,
                      normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12), 0)
    depth = rng.uniform(0.9, 1.0, (h * k, w * k)).astype(np.float32)
    rgb = np.zeros((h * k, w * k, 3), np.uint8)
    for size in ((h, w), (h * k * k, w * k * k)):
        _, _, n2, _ = resize_rgbdn(rgb, depth, normal.astype(np.float32), camera(h * k, w * k), *size)
        length = np.linalg.norm(n2, axis=-1)
        assert np.all((np.abs(length - 1) < 1e-5) | (length == 0))


@settings(max_examples=20, deadline=None)
@given(h=SIZES, w=SIZES, k=FACTORS)
def test_intrinsics_follow_pixel_centres(h, w, k):
    """A shrunk pixel's ray is the ray through its block's centre; K survives a round trip."""
    K = camera(h * k, w * k)
    K2 = scale_intrinsics(K, Fraction(1, k))
    ray = unproject_depth(np.ones((h, w)), K2)[1, 1]
    expected = [(1.5 * k - K[0, 2]) / K[0, 0], (1.5 * k - K[1, 2]) / K[1, 1], 1.0]
    np.testing.assert_allclose(ray, expected, atol=1e-6)
    np.testing.assert_allclose(scale_intrinsics(K2, k), K, rtol=1e-12)
    rgb, depth, normal, _, _, _ = plane_frame(h * k, w * k, 0, 0, 1.0)
    _, _, _, K_small = resize_rgbdn(rgb, depth, normal, K, h, w)
    _, _, _, K_back = resize_rgbdn(*resize_rgbdn(rgb, depth, normal, K, h, w)[:3], K_small, h * k, w * k)
    np.testing.assert_allclose(K_back, K, rtol=1e-12)


def test_rgb_is_area_averaged_when_shrinking_and_bilinear_when_enlarging():
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[:2, :2] = 200  # one 2x2 block
    rgb[2:, 2:] = (10, 20, 30)
    rgb[0, 2] = 100  # a quarter of its block
    depth, normal = np.ones((4, 4), np.float32), np.broadcast_to(np.float32([0, 0, -1]), (4, 4, 3)).copy()
    small, _, _, _ = resize_rgbdn(rgb, depth, normal, camera(4, 4), 2, 2)
    assert small.dtype == np.uint8
    np.testing.assert_array_equal(small[..., 0], [[200, 25], [0, 10]])
    big, _, _, _ = resize_rgbdn(small, depth[:2, :2], normal[:2, :2], camera(2, 2), 4, 4)
    # Output column 1 lies a quarter of the way from input column 0 to 1; row 0 replicates the edge.
    assert big[0, 0, 0] == 200 and big[0, 1, 0] == round(0.75 * 200 + 0.25 * 25)


def test_an_enlarged_plane_is_that_plane_not_a_staircase():
    """Away from the border, enlarging interpolates inverse depth, which is exact on a plane."""
    rgb, depth, normal, K, m, c = plane_frame(32, 32, 20.0, 40.0, 1.0)
    _, depth2, _, K2 = resize_rgbdn(rgb, depth, normal, K, 64, 64)
    true, _ = plane_depth(m, c, K2, *pixel_grid(64, 64))
    np.testing.assert_allclose(depth2[1:-1, 1:-1], true[1:-1, 1:-1], rtol=1e-5)
