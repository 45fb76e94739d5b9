"""Believability measures (tesseract4d/evaluation/believability.py) on images with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from tesseract4d.evaluation.believability import (
    edge_sharpness, instruction_contrast, objects_present, token_grid_ratio,
)


def _scene(frames: int = 6, size: int = 64, cube_px: int = 6, step_px: int = 2):
    """A shaded table with a red cube sliding right and a blue cube standing still; segmentation ids 1, 2."""
    v, u = np.mgrid[0:size, 0:size]
    rgb = np.zeros((frames, size, size, 3), np.uint8)
    seg = np.zeros((frames, size, size), np.int32)
    for t in range(frames):
        rgb[t] = np.stack([90 + 40 * v / size, 80 + 30 * u / size, 70 + 0 * u], -1).astype(np.uint8)
        x = 10 + step_px * t
        rgb[t, 20:20 + cube_px, x:x + cube_px] = (220, 30, 30)
        seg[t, 20:20 + cube_px, x:x + cube_px] = 1
        rgb[t, 40:40 + cube_px, 40:40 + cube_px] = (30, 40, 220)
        seg[t, 40:40 + cube_px, 40:40 + cube_px] = 2
    return rgb, seg


def test_token_grid_is_about_one_for_a_real_image_and_large_for_blocks():
    import cv2

    rng = np.random.default_rng(0)
    # A real image's edges fall anywhere: blurred noise, whose statistics ignore any grid.
    real = np.stack([cv2.GaussianBlur(rng.normal(128, 60, (64, 64, 3)), (0, 0), 1.5) for _ in range(4)])
    assert 0.85 < token_grid_ratio(real.clip(0, 255).astype(np.uint8), 4) < 1.15
    smooth = rng.normal(128, 30, (3, 16, 16, 3)).clip(0, 255)
    blocks = np.kron(smooth, np.ones((1, 4, 4, 1))).astype(np.uint8)  # each 4x4 block one colour
    assert token_grid_ratio(blocks, 4) > 20
    with pytest.raises(ValueError):
        token_grid_ratio(blocks, 1)


def test_edge_sharpness_is_one_for_the_truth_and_drops_with_blur():
    import cv2

    rgb, _ = _scene()
    assert edge_sharpness(rgb, rgb) == pytest.approx(1.0)
    blurred = np.stack([cv2.GaussianBlur(f, (0, 0), 2.0) for f in rgb])
    assert edge_sharpness(blurred, rgb) < 0.6


def test_objects_present_finds_kept_shifted_and_lost_objects():
    gt, seg = _scene()
    both = objects_present(gt, seg, [1, 2], gt)
    assert both.frames_all_present == 1.0 and both.per_object == {1: 1.0, 2: 1.0} and both.judged_frames == 6
    # One pixel off is still where it should be.
    shifted = np.roll(gt, 1, axis=2)
    assert objects_present(gt, seg, [1, 2], shifted).frames_all_present == 1.0
    # The red cube dissolved into the table from frame 3 on: those frames fail, the blue cube is kept.
    lost = gt.copy()
    for t in range(3, 6):
        lost[t][seg[t] == 1] = gt[t][~(seg[t] > 0)].reshape(-1, 3)[:int((seg[t] == 1).sum())]
    r = objects_present(gt, seg, [1, 2], lost)
    assert r.frames_all_present == pytest.approx(0.5) and r.per_object[1] == pytest.approx(0.5) and r.per_object[2] == 1.0
    # A red cube drawn far from where it should be does not count.
    far = lost.copy()
    far[:, 2:8, 50:56] = (220, 30, 30)
    assert objects_present(gt, seg, [1], far).per_object[1] == pytest.approx(0.5)


def test_instruction_contrast_scores_direction_and_stillness():
    group = [
        {"instruction": "push the red cube left", "still": False, "commanded_px": (-10, 0), "predicted_px": (-6, 1), "motion": 8.0},
        {"instruction": "push the red cube right", "still": False, "commanded_px": (10, 0), "predicted_px": (-6, 1), "motion": 8.0},
        {"instruction": "keep the arm still", "still": True, "commanded_px": None, "predicted_px": (0, 0), "motion": 0.5},
    ]
    r = instruction_contrast(group)
    assert (r.instructions, r.right) == (3, 2) and r.share == pytest.approx(2 / 3)
    assert [row["right"] for row in r.per_instruction] == [True, False, True]
    group[2]["motion"] = 4.0  # half the active motion: not still
    assert instruction_contrast(group).right == 1
