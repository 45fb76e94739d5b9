"""Drift curves (evaluation/horizon.py) are exact on synthetic sequences whose errors are known per frame."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still

from tesseract4d import dataset_format as df
from tesseract4d.evaluation.heldout import static_world
from tesseract4d.evaluation.horizon import (
    build_report, episode_curves, format_markdown, frame_curves, mean_curves, object_error_curve, object_paths,
    segment_following, summarize, window_frames, write_horizon_report,
)
from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment

T = 8


def _boxes(red_shown=None):
    red = Box("cube_red", moving((0.0, -0.04, 0.02), (0.0, 0.06, 0.02), T, first=1), np.zeros(T), (0.02, 0.02, 0.02),
              (200, 30, 30), shown=red_shown)
    green = Box("cube_green", still((0.08, 0.05, 0.02), T), np.zeros(T), (0.02, 0.02, 0.02), (30, 180, 40))
    return [red, green]


@pytest.fixture(scope="module")
def truth():
    return box_episode(_boxes(), T, size=64)


def test_psnr_and_abs_rel_follow_the_errors_put_in(truth):
    gt = truth.cameras["close"]
    offset = np.arange(T)  # RGB off by t levels in frame t (below the colour tolerance: objects stay found)
    scale = 0.01 * np.arange(T)  # depth too far by 1 % per frame
    assert int(gt.rgb.max()) + T <= 255  # no clipping: the error is exactly the offset
    pred = dataclasses.replace(gt, rgb=(gt.rgb.astype(np.int32) + offset[:, None, None, None]).astype(np.uint8),
                               depth_m=gt.depth_m * (1 + scale[:, None, None]).astype(np.float32))
    curves = frame_curves(pred, gt)
    assert math.isnan(curves["rgb_psnr_db_moving"][0]) and math.isnan(curves["depth_abs_rel"][0])  # frame 0 is given
    # the red cube starts moving after frame 1: frame 1 has no moving region to score
    assert math.isnan(curves["rgb_psnr_db_moving"][1])
    np.testing.assert_allclose(curves["rgb_psnr_db_moving"][2:], 20 * np.log10(255.0 / offset[2:]), rtol=1e-9)
    np.testing.assert_allclose(curves["depth_abs_rel"][1:], scale[1:], rtol=1e-5)
    np.testing.assert_array_equal(curves["objects_present"][1:], np.ones(T - 1))


def test_permanence_drops_by_the_share_of_objects_lost(truth):
    gt = truth.cameras["close"]
    shown = np.arange(T) < 5  # the red cube vanishes from frame 5 on
    pred = box_episode(_boxes(red_shown=shown), T, size=64).cameras["close"]
    present = frame_curves(pred, gt)["objects_present"]
    np.testing.assert_array_equal(present[1:], np.where(shown, 1.0, 0.5)[1:])


def test_the_static_worlds_object_error_is_the_truths_displacement(truth):
    err = object_error_curve(object_paths(static_world(truth, "close", T), truth, "close"), truth)
    red = truth.object_poses["cube_red"][:, :3]
    moved = np.linalg.norm(red - red[0], axis=1)
    # two objects: the red one's error is how far it went, the green one's 0
    np.testing.assert_allclose(err, moved / 2, atol=1e-4)
    assert moved[-1] > 0.09  # the red cube went 10 cm
    assert object_paths(truth, dataclasses.replace(truth, object_poses={}), "close") is None  # nothing recorded
    assert object_error_curve(None, truth) is None


def test_a_segment_is_followed_when_its_object_moves_the_commanded_way(truth):
    push = {"skill": "push", "target": "cube_red", "commanded_displacement_world_m": [0.0, 0.1, 0.0]}
    wrong = dict(push, commanded_displacement_world_m=[0.1, 0.0, 0.0])  # forward: the truth went left
    reach = {"skill": "reach", "target": None, "commanded_displacement_world_m": [0.0, 0.0, 0.0]}
    # the red cube moves 10 cm left over frames 1-7: 6.7 cm by frame 5, 3.3 cm from 5 to 7
    schedule = [Segment("push the red cube left", 0, 5, push), Segment("reach left", 5, 6, reach),
                Segment("push the red cube left", 5, 7, push), Segment("push the red cube forward", 0, 7, wrong)]
    on_truth = object_paths(truth, truth, "close")  # the tracker on the truth's own frames
    assert segment_following(on_truth, schedule) == [True, None, False, False]  # less than half is not followed
    assert segment_following(object_paths(static_world(truth, "close", T), truth, "close"), schedule[:1]) == [False]
    chained = dataclasses.replace(truth, metadata={SCHEDULE_KEY: [s.to_dict() for s in schedule[:2]]})
    assert episode_curves(truth, chained, "close", 1.5)["followed"] == [True, None]


def test_pooling_windows_and_segments():
    a = {"rgb_psnr_db_moving": np.array([np.nan, 20, 18, 16, 14, 12]), "depth_abs_rel": np.full(6, 0.1),
         "objects_present": np.array([np.nan, 1, 1, 1, 0.5, 0.5]), "object_error_m": np.full(6, np.nan)}
    b = {"rgb_psnr_db_moving": np.array([np.nan, 22, 20, 18]), "depth_abs_rel": np.full(4, 0.3),
         "objects_present": np.array([np.nan, 1, np.nan, 1]), "object_error_m": np.full(4, np.nan)}
    mean = mean_curves([a, b])
    np.testing.assert_allclose(mean["rgb_psnr_db_moving"]["mean"][1:], [21, 19, 17, 14, 12])
    assert mean["rgb_psnr_db_moving"]["episodes"] == [0, 2, 2, 2, 1, 1]
    np.testing.assert_allclose(mean["objects_present"]["mean"][1:], [1, 1, 1, 0.5, 0.5])
    assert window_frames(6, 3) == {"first": [1, 2], "last": [4, 5]}
    s = summarize(mean, 6, 3)
    assert s["rgb_psnr_db_moving"]["first"] == pytest.approx(20) and s["rgb_psnr_db_moving"]["last"] == pytest.approx(13)
    assert s["rgb_psnr_db_moving"]["change"] == pytest.approx(-7) and s["objects_present"]["ratio"] == pytest.approx(0.5)
    assert math.isnan(s["object_error_m"]["first"])
    report = build_report(None, {"model": [a, b], "static": [b, a]}, [[Segment("x", 0, 3), Segment("y", 3, 5)], None],
                          [{"frames": 6}, {"frames": 4}], 3, 1.5)
    segs = report["methods"]["model"]["segments"]
    # only the first episode is chained: segment 1 = frames 1-3, segment 2 = frames 4-5 of it
    assert segs[0]["rgb_psnr_db_moving"] == pytest.approx(18) and segs[1]["rgb_psnr_db_moving"] == pytest.approx(13)
    assert segs[1]["objects_present"] == pytest.approx(0.5) and segs[0]["episodes"] == 1
    text = format_markdown(report)
    assert "| RGB PSNR, moving region | model | 20.00 | 13.00 | -7.00 dB |" in text
    assert "×0.50" in text


def test_report_files(tmp_path, truth):
    curves = [episode_curves(static_world(truth, "close", T), truth, "close", 1.5)]
    report = build_report(None, {"model": curves, "static": curves}, [None], [{"frames": T}], 4, 1.5)
    write_horizon_report(report, tmp_path)
    assert json.loads((tmp_path / "horizon.json").read_text())["num_frames"] == T
    assert (tmp_path / "horizon.md").read_text().startswith("# Drift over 8 frames")
    import cv2

    image = cv2.imread(str(tmp_path / "horizon.png"))
    assert image is not None and image.shape[0] > 200 and image.std() > 5  # a drawn plot, not a blank


def test_evaluate_horizon_command_writes_its_report(micro_checkpoint, tmp_path, capsys):
    from tesseract4d import cli
    from tesseract4d.testing.synthetic_scene import synthetic_episode

    data = tmp_path / "heldout"
    df.init_dataset(data, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    chained = synthetic_episode(0, frames=15)
    schedule = [Segment("push the square to the right", 0, 7), Segment("push the square to the left", 7, 14)]
    df.write_episode(data, dataclasses.replace(chained, metadata={SCHEDULE_KEY: [s.to_dict() for s in schedule]}))
    df.write_episode(data, synthetic_episode(1, frames=15, direction=-1))  # one instruction, no schedule
    out = tmp_path / "horizon"
    assert cli.main(["evaluate", "--horizon", "--heldout", str(data), "--checkpoint", str(micro_checkpoint),
                     "--steps", "1", "--out", str(out)]) == 0
    report = json.loads((out / "horizon.json").read_text())
    assert report["num_frames"] == 15 and report["clip_frames"] == 8 and len(report["episodes"]) == 2
    assert [e["segments"] for e in report["episodes"]] == [2, 1]
    model = report["methods"]["model"]
    assert len(model["curves"]["depth_abs_rel"]["mean"]) == 15 and model["curves"]["depth_abs_rel"]["episodes"][1:] == [2] * 14
    assert model["summary"]["windows"] == {"first": [1, 7], "last": [8, 14]}
    assert [r["segment"] for r in model["segments"]] == [1, 2]  # the chained episode's segments
    assert (out / "horizon.png").stat().st_size > 1000 and "# Drift over 15 frames" in (out / "horizon.md").read_text()
    assert "| depth AbsRel | static |" in capsys.readouterr().out
    assert cli.main(["evaluate", "--horizon", "--out", str(tmp_path / "x")]) == 2
    assert "--horizon scores a held-out dataset" in capsys.readouterr().err
