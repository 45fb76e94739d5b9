"""Metrics (pure functions) and the evaluation report."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from tesseract4d.evaluation import metrics as M
from tesseract4d.evaluation.episode import evaluate_episode, format_report, json_safe
from reconstruction.reconstruct import ReconConfig, reconstruct_episode
from tesseract4d.errors import UserError
from tesseract4d.testing.synthetic_scene import analytic_episode


def test_chamfer_identity_shift_and_empty():
    rng = np.random.default_rng(0)
    a = rng.uniform(-1, 1, (500, 3))
    assert M.chamfer_l1_m(a, a) == 0.0
    # A far-away copy: every nearest neighbour is the shifted twin, at exactly the shift.
    shift = np.array([0.0, 0.0, 10.0])
    assert M.chamfer_l1_m(a, a + shift) == pytest.approx(10.0, abs=2.0)
    two = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    assert M.chamfer_l1_m(two, two + [0, 0.3, 0]) == pytest.approx(0.3)
    # One extra point 1 m away: 0 one way, 1/3 the other way -> mean of both = 1/6.
    assert M.chamfer_l1_m(two, np.vstack([two, [[0, 1.0, 0]]])) == pytest.approx(1 / 6)
    assert np.isnan(M.chamfer_l1_m(np.zeros((0, 3)), two))


def test_depth_metrics_values_and_validity():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])
    pred = np.array([[1.1, 2.0], [8.0, 3.0]])  # last pixel: gt has no depth -> ignored
    d = M.depth_metrics(pred, gt)
    assert d["abs_rel"] == pytest.approx((0.1 + 0 + 1.0) / 3)
    assert d["delta1"] == pytest.approx(2 / 3) and d["delta2"] == pytest.approx(2 / 3)
    masked = M.depth_metrics(pred, gt, mask=np.array([[True, False], [False, False]]))
    assert masked["abs_rel"] == pytest.approx(0.1)
    empty = M.depth_metrics(pred, gt, mask=np.zeros((2, 2), bool))
    assert all(np.isnan(v) for v in empty.values())
    nan_pred = M.depth_metrics(np.full((2, 2), np.nan), gt)
    assert np.isnan(nan_pred["abs_rel"])
    with pytest.raises(ValueError):
        M.depth_metrics(pred, gt, mask=np.ones((3, 3), bool))


def test_normal_metrics():
    gt = np.zeros((2, 2, 3))
    gt[..., 2] = -1
    pred = gt.copy()
    pred[0, 0] = [1, 0, 0]  # 90 degrees
    pred[1, 1] = 0  # no normal -> ignored
    n = M.normal_metrics(pred, gt)
    assert n["mean_deg"] == pytest.approx(30.0)
    assert n["median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert n["within_11_25"] == pytest.approx(2 / 3)
    assert np.isnan(M.normal_metrics(pred, gt, mask=np.zeros((2, 2), bool))["mean_deg"])


def test_psnr_and_ssim():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    assert M.rgb_psnr(img, img) == M.PSNR_MAX_DB
    off = np.clip(img.astype(int) + 10, 0, 255).astype(np.uint8)
    mse = np.mean((off.astype(float) - img) ** 2)
    assert M.rgb_psnr(off, img) == pytest.approx(10 * np.log10(255**2 / mse))
    assert M.rgb_ssim(img, img) == pytest.approx(1.0)
    noisy = np.clip(img + rng.normal(0, 40, img.shape), 0, 255).astype(np.uint8)
    s = M.rgb_ssim(noisy, img)
    assert 0 < s < 0.9
    assert M.rgb_ssim(img, noisy) == pytest.approx(s, rel=1e-6)  # symmetric
    assert M.rgb_ssim(img / 255.0, noisy / 255.0) == pytest.approx(s, rel=1e-6)  # float images: peak 1
    assert np.isnan(M.rgb_psnr(img, img, mask=np.zeros((32, 32), bool)))


def test_moving_region_mask_of_sliding_box():
    ep = analytic_episode(num_frames=6, height=48, width=48)
    moving = M.moving_region_mask(ep.cameras["base_camera"])
    assert moving.shape == (6, 48, 48)
    assert moving[1:].any(axis=(1, 2)).all()
    assert (moving[0] == moving[1:].any(0)).all()
    assert moving.mean() < 0.3  # the table stays still
    still = copy.deepcopy(ep.cameras["base_camera"])
    still.rgb[:], still.depth_m[:] = still.rgb[:1], still.depth_m[:1]
    assert not M.moving_region_mask(still).any()
    # A few pixels of render noise (a speck in frame 0 only) are no motion: the region stays empty ...
    n = M.MIN_MOVING_PIXELS_PER_FRAME
    speck = copy.deepcopy(still)
    speck.rgb[0, 10, 10:10 + n - 1] = 255 - still.rgb[0, 10, 10:10 + n - 1]
    assert not M.moving_region_mask(speck).any()
    # ... while as many pixels per frame as MIN_MOVING_PIXELS_PER_FRAME make one.
    speck.rgb[0, 10, 10:10 + n] = 255 - still.rgb[0, 10, 10:10 + n]
    assert M.moving_region_mask(speck).sum() == n * 6


@pytest.fixture(scope="module")
def scene():
    return analytic_episode(num_frames=8, height=48, width=48)


def test_evaluate_ground_truth_against_itself(scene):
    report = evaluate_episode(scene, scene)
    mean = report["mean"]
    assert report["num_frames"] == 8 and len(report["per_frame"]) == 8
    assert mean["chamfer_l1_m"] == 0 and mean["chamfer_l1_m_moving"] == 0
    assert mean["depth_abs_rel"] == 0 and mean["depth_delta1"] == 1
    assert mean["normal_mean_deg"] < 1e-3 and mean["rgb_ssim"] == pytest.approx(1.0)
    assert 0 < mean["moving_share"] < 0.3
    text = format_report(report)
    assert "chamfer_l1_m" in text and "moving" in text


def test_evaluate_reconstruction_and_report_shape_for_viewer(scene, tmp_path):
    from viewer.compare import load_report_per_frame

    recon = reconstruct_episode(scene, config=ReconConfig(fuse_background=False))
    report = evaluate_episode(recon, scene)
    assert report["mean"]["chamfer_l1_m"] < 0.01
    path = tmp_path / "report.json"
    path.write_text(json.dumps(json_safe(report)))
    rows = load_report_per_frame(path)
    assert len(rows) == 8 and "chamfer_l1_m" in rows[0] and "rgb_psnr_db_moving" in rows[0]


def test_evaluate_empty_moving_mask_gives_null(scene):
    report = evaluate_episode(scene, scene, moving_mask=np.zeros((8, 48, 48), bool))
    assert np.isnan(report["mean"]["depth_abs_rel_moving"])
    assert json_safe(report)["mean"]["chamfer_l1_m_moving"] is None
    json.dumps(json_safe(report), allow_nan=False)


def test_evaluate_bad_inputs(scene):
    short = copy.deepcopy(scene)
    cam = short.cameras["base_camera"]
    for name in ("rgb", "depth_m", "normal_cam", "K", "T_world_cam"):
        setattr(cam, name, getattr(cam, name)[:5])
    short.frame_steps = short.frame_steps[:5]
    report = evaluate_episode(short, scene)  # a shorter prediction: its frames are evaluated
    assert report["num_frames"] == 5 and report["gt_frames"] == 8
    small = analytic_episode(num_frames=8, height=32, width=32)
    with pytest.raises(UserError, match="resolution"):
        evaluate_episode(small, scene)
    with pytest.raises(UserError, match="no camera"):
        evaluate_episode(scene, scene, camera="wrist")
    with pytest.raises(UserError, match="moving mask"):
        evaluate_episode(scene, scene, moving_mask=np.zeros((8, 10, 10), bool))
