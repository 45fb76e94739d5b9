"""The instruction-following measure on an analytic scene: a red cube moving right past a red
goal marker, seen by a pinhole camera at the world origin."""

from __future__ import annotations

import numpy as np
import pytest

from tesseract4d.evaluation.instruction_following import direction_score, object_pixel_track, summarize

H = W = 64
K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
T_WORLD_CAM = np.eye(4)
CUBE_ID, GOAL_ID = 18, 19
SEG_NAMES = {0: "background", CUBE_ID: "cube", GOAL_ID: "goal_region"}


def _frame(cube_uv, goal_uv=(12, 50)):
    rgb = np.full((H, W, 3), 120, np.uint8)
    seg = np.zeros((H, W), np.int32)
    for (u, v), colour, sid in ((goal_uv, (200, 30, 30), GOAL_ID), (cube_uv, (210, 25, 25), CUBE_ID)):
        u, v = int(round(u)), int(round(v))
        rgb[v - 2:v + 3, u - 2:u + 3] = colour
        seg[v - 2:v + 3, u - 2:u + 3] = sid
    return rgb, seg


def _scene(dx_m=0.2, frames=8):
    xyz = np.stack([np.linspace(0, dx_m, frames), np.zeros(frames), np.ones(frames)], axis=1)
    poses = np.concatenate([xyz, np.tile([1.0, 0, 0, 0], (frames, 1))], axis=1)  # (T, 7)
    uv = object_pixel_track(poses, K, T_WORLD_CAM)
    rgb, seg = zip(*(_frame(p) for p in uv))
    return np.stack(rgb), np.stack(seg), poses, uv


def _score(rgb, seg, poses, pred_last):
    return direction_score("PushCube-v1", rgb, seg, SEG_NAMES, poses, K, T_WORLD_CAM, pred_last)


def test_pixel_track_projects_the_pose():
    _, _, _, uv = _scene(dx_m=0.2)
    assert uv[0] == pytest.approx([32.0, 32.0])
    assert uv[-1] == pytest.approx([42.0, 32.0])  # 50 px/m * 0.2 m at 1 m depth


def test_ground_truth_scores_one_static_scores_zero_opposite_scores_minus_one():
    rgb, seg, poses, uv = _scene()
    truth = _score(rgb, seg, poses, rgb[-1])
    assert truth.valid and truth.cosine > 0.99 and truth.endpoint_error_px < 0.5
    static = _score(rgb, seg, poses, rgb[0])
    assert static.valid and static.cosine == 0.0
    assert static.endpoint_error_px == pytest.approx(10.0, abs=0.5)
    opposite, _ = _frame((uv[0][0] - 10, uv[0][1]))
    back = _score(rgb, seg, poses, opposite)
    assert back.cosine < -0.99
    summary = summarize([truth, static, back])
    assert summary["episodes"] == 3 and summary["right_way"] == pytest.approx(1 / 3)


def test_blurred_prediction_still_tracked():
    import cv2

    rgb, seg, poses, _ = _scene()
    blurred = cv2.GaussianBlur(rgb[-1], (3, 3), 0.8)
    assert _score(rgb, seg, poses, blurred).cosine > 0.95


def test_no_true_motion_is_not_scored():
    rgb, seg, poses, _ = _scene(dx_m=0.0)
    s = _score(rgb, seg, poses, rgb[-1])
    assert not s.valid
    assert summarize([s]) == {"episodes": 0}
