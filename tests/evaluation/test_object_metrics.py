"""Object-track metrics (tesseract4d/evaluation/object_tracks.py) are exact on synthetic truth: the
truth's own layer scores zero, known shifts and turns of a track score exactly their size."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from reconstruction.objects import STATES, episode_objects, rotation_about
from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still
from tesseract4d.evaluation.object_tracks import format_rows, object_track_metrics, pooled

T = 8
HALF = 0.02


@pytest.fixture(scope="module")
def scene():
    red = Box("cube_red", moving((0.0, 0.0, HALF), (0.08, 0.02, HALF), T), np.linspace(0, 0.3, T), (HALF,) * 3, (220, 30, 30))
    green = Box("cube_green", still((-0.05, -0.09, HALF), T), np.zeros(T), (HALF,) * 3, (30, 200, 40))
    gt = box_episode([red, green], T, intent={"skill": "push", "target": "cube_red"})
    return gt, episode_objects(gt, "close", truth=True)


def test_the_truths_own_layer_scores_zero(scene):
    gt, layer = scene
    m = object_track_metrics(layer, gt)
    assert m["instructed"] == "cube_red" and m["missing"] == []
    for r in m["per_object"].values():
        assert r["final_error_m"] < 1e-6 and r["mean_error_m"] < 1e-6 and r["yaw_error_deg"] < 1e-4
    s = m["summary"]
    assert s["instructed_within_2cm"] == 1.0 and s["others_still_within_1cm"] == 1.0 and s["within_5mm"] == 1.0
    assert s["others_still"] == 1 and s["lost_share"] == 0.0
    assert math.isclose(m["per_object"]["cube_red"]["displacement_truth_m"], math.hypot(0.08, 0.02), rel_tol=1e-6)
    assert "cube_red" in format_rows(m)


def test_known_shifts_and_turns_score_their_size(scene):
    gt, layer = scene
    moved = copy.deepcopy(layer)
    red = moved.track("cube_red")
    red.T_world_object[-1, :3, 3] += [0.015, 0.0, 0.0]  # ends 15 mm off: within 2 cm
    red.T_world_object[3, :3, 3] += [0.0, 0.03, 0.0]  # one frame 30 mm off
    m = object_track_metrics(moved, gt)
    r = m["per_object"]["cube_red"]
    assert math.isclose(r["final_error_m"], 0.015, abs_tol=1e-6) and math.isclose(r["displacement_error_m"], 0.015, abs_tol=1e-6)
    assert math.isclose(r["mean_error_m"], (0.015 + 0.03) / (T - 1), abs_tol=1e-6)  # frames 1 on
    assert m["summary"]["instructed_within_2cm"] == 1.0
    red.T_world_object[-1, :3, 3] += [0.01, 0.0, 0.0]  # now 25 mm off
    assert object_track_metrics(moved, gt)["summary"]["instructed_within_2cm"] == 0.0

    # A turn of 10 degrees about the recorded object's origin: yaw error 10, no position error.
    turned = copy.deepcopy(layer)
    tr = turned.track("cube_red")
    pivot = gt.object_poses["cube_red"][-1, :3].astype(np.float64)
    turn = np.eye(4)
    turn[:3, :3] = rotation_about(np.array([0.0, 0.0, 1.0]), np.deg2rad(10))
    turn[:3, 3] = pivot - turn[:3, :3] @ pivot
    tr.T_world_object[-1] = turn @ tr.T_world_object[-1]
    r = object_track_metrics(turned, gt)["per_object"]["cube_red"]
    assert math.isclose(r["yaw_error_deg"], 10.0, abs_tol=1e-6) and r["final_error_m"] < 1e-6

    # The still green cube drifting 12 mm in one frame fails "stayed within 1 cm"; 8 mm does not.
    drift = copy.deepcopy(layer)
    drift.track("cube_green").T_world_object[2, :3, 3] += [0.0, 0.012, 0.0]
    assert object_track_metrics(drift, gt)["summary"]["others_still_within_1cm"] == 0.0
    drift.track("cube_green").T_world_object[2, :3, 3] -= [0.0, 0.004, 0.0]
    assert object_track_metrics(drift, gt)["summary"]["others_still_within_1cm"] == 1.0


def test_a_missing_object_fails_and_tracks_match_by_position(scene):
    gt, layer = scene
    renamed = copy.deepcopy(layer)
    renamed.tracks[0].name = "red object"  # as the colour finder names it: matched by position
    renamed.tracks.pop(1)  # the green cube has no track
    m = object_track_metrics(renamed, gt)
    assert m["per_object"]["cube_red"]["track"] == "red object" and m["missing"] == ["cube_green"]
    assert m["summary"]["others_still_within_1cm"] == 0.0 and m["summary"]["within_5mm"] == 0.5
    p = pooled([m, object_track_metrics(layer, gt)])
    assert p["instructed"] == 2 and p["instructed_within_2cm"] == 1.0
    assert p["others_still"] == 2 and p["others_still_within_1cm"] == 0.5 and p["within_5mm"] == 0.75


def test_keep_still_has_no_instructed_object(scene):
    gt, layer = scene
    still_gt = copy.deepcopy(gt)
    still_gt.intent = {"skill": "keep_still"}
    m = object_track_metrics(layer, still_gt)
    assert m["instructed"] is None and math.isnan(m["summary"]["instructed_within_2cm"])
    assert m["summary"]["others_still"] == 1  # the red cube moved in the truth: not a still one


def test_the_seen_only_row_leaves_out_what_the_layer_inferred(scene):
    # The red cube is placed right at the end but only inferred after frame 3 (where the layer last saw it):
    # the instructed row counts it, the seen-only row does not.
    gt, layer = scene
    inferred = copy.deepcopy(layer)
    red = inferred.track("cube_red")
    red.state[4:] = STATES.index("inferred")
    m = object_track_metrics(inferred, gt)
    s, r = m["summary"], m["per_object"]["cube_red"]
    assert s["instructed_within_2cm"] == 1.0 and s["instructed_seen_within_2cm"] == 0.0
    assert r["last_seen_frame"] == 3 and r["inferred_frames"] == T - 4
    assert math.isclose(s["inferred_share"], (T - 4) / (2 * T))
    pose = gt.object_poses["cube_red"]
    assert math.isclose(r["seen_final_error_m"], float(np.linalg.norm(pose[-1, :3] - pose[3, :3])), abs_tol=1e-6)
    assert pooled([m])["instructed_seen_within_2cm"] == 0.0


def test_an_object_carried_out_of_view_is_counted_apart(scene):
    # The truth carries the red cube behind the camera at the last frame: no tracker of these frames can
    # place it, so "within 5 mm" is also given over the objects in view at the end.
    gt, layer = scene
    gone = copy.deepcopy(gt)
    gone.object_poses["cube_red"] = gone.object_poses["cube_red"].copy()
    gone.object_poses["cube_red"][-1, :3] = [0.6, -0.6, 0.6]  # behind the camera at (0.30, -0.30, 0.32)
    m = object_track_metrics(layer, gone)
    assert m["per_object"]["cube_red"]["in_view_at_end"] is False and m["per_object"]["cube_green"]["in_view_at_end"] is True
    s = m["summary"]
    assert s["within_5mm"] == 0.5 and s["objects_in_view"] == 1 and s["within_5mm_in_view"] == 1.0
    aside = copy.deepcopy(gt)
    aside.object_poses["cube_red"] = aside.object_poses["cube_red"].copy()
    aside.object_poses["cube_red"][-1, :3] = [0.3, 0.5, 0.02]  # in front of the camera, far outside its 50 degrees
    assert object_track_metrics(layer, aside)["per_object"]["cube_red"]["in_view_at_end"] is False
    p = pooled([m, object_track_metrics(layer, gt)])
    assert p["objects"] == 4 and p["within_5mm"] == 0.75 and p["objects_in_view"] == 3 and p["within_5mm_in_view"] == 1.0
