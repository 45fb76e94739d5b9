"""Believability measures in the held-out evaluation: synthetic counterfactual groups with known
motion (no simulator), scored as the ground truth, as the static world, and by two checkpoints
side by side."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tesseract4d import dataset_format as df
from tesseract4d.evaluation.heldout_believability import (breakdown, clip_motion, commanded_px, contrast_by_group,
                                                          contrast_entry, episode_believability, scene_object_ids)

SIZE, FRAMES, F_PX = 32, 8, 32.0  # image size, frames, focal length (pixels); the scene lies at 1 m
SEG = {0: "background", 3: "panda_hand", 5: "table-workspace", 6: "goal_region", 18: "red_cube", 19: "green_cube"}
OBJECTS = {"red_cube": (18, (220, 30, 30), (6, 10)), "green_cube": (19, (30, 200, 30), (20, 22))}  # id, colour, (u0, v0)
# (instruction, skill, target, commanded displacement in world metres = camera metres here)
GROUP = (
    ("push the red cube to the right", "push", "red_cube", (0.5, 0.0, 0.0)),
    ("push the green cube up", "push", "green_cube", (0.0, -0.5, 0.0)),
    ("keep still", "keep_still", None, (0.0, 0.0, 0.0)),
)


def group_episode(k: int, seed: int = 100000) -> df.Episode:
    """Episode k of a synthetic group: two 8-px squares on a grey plane 1 m in front of the camera
    (T_world_cam = identity, so world metres map to f pixels); the instructed one moves
    ``commanded * f`` pixels over the clip, the other stays; a grey robot block stays too."""
    instruction, skill, target, cmd = GROUP[k]
    K = np.array([[F_PX, 0, SIZE / 2], [0, F_PX, SIZE / 2], [0, 0, 1]])
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    rgb = np.zeros((FRAMES, SIZE, SIZE, 3), np.uint8)
    seg = np.zeros((FRAMES, SIZE, SIZE), np.int32)
    poses = {name: np.zeros((FRAMES, 7), np.float32) for name in OBJECTS}
    for t in range(FRAMES):
        rgb[t] = (60 + 60 * v[..., None] / SIZE).astype(np.uint8)
        seg[t] = 5
        rgb[t, 26:, :6], seg[t, 26:, :6] = 90, 3  # a robot link: not a scene object
        for name, (oid, colour, (u0, v0)) in OBJECTS.items():
            shift = np.asarray(cmd[:2]) * F_PX * t / (FRAMES - 1) if name == target else np.zeros(2)
            uu, vv = int(round(u0 + shift[0])), int(round(v0 + shift[1]))
            rgb[t, vv:vv + 8, uu:uu + 8], seg[t, vv:vv + 8, uu:uu + 8] = colour, oid
            poses[name][t] = [(uu + 3.5 - SIZE / 2) / F_PX, (vv + 3.5 - SIZE / 2) / F_PX, 1.0, 1, 0, 0, 0]
    cam = df.CameraFrames(rgb=rgb, depth_m=np.ones((FRAMES, SIZE, SIZE), np.float32),
                          normal_cam=np.broadcast_to(np.float32([0, 0, -1]), (FRAMES, SIZE, SIZE, 3)).copy(),
                          K=np.repeat(K[None], FRAMES, 0), T_world_cam=np.repeat(np.eye(4)[None], FRAMES, 0),
                          segmentation=seg, seg_id_to_name=dict(SEG))
    intent = {"skill": skill, "variant": skill if skill == "keep_still" else f"{skill}_{k}", "target": target,
              "other": None, "commanded_displacement_world_m": list(cmd), "gripper_goal_world_m": None}
    return df.Episode(env_id="Synthetic-v0", seed=seed, instruction=instruction, cameras={"close": cam},
                      frame_steps=np.arange(FRAMES, dtype=np.int32), object_poses=poses, success=True,
                      variant=k, intent=intent)


def static(rgb: np.ndarray) -> np.ndarray:
    return np.repeat(rgb[:1], len(rgb), axis=0)


def test_scene_objects_leave_out_robot_table_ground_and_goals():
    assert scene_object_ids(SEG) == [18, 19]
    pick = {0: "background", 16: "table-workspace", 17: "ground", 18: "cube", 19: "goal_site", 1: "panda_link0",
            14: "camera_link", 12: "panda_leftfinger"}
    assert scene_object_ids(pick) == [18]
    assert scene_object_ids({18: "cube", 19: "l_shape_tool", 20: "goal_marker", 21: "red_cylinder"}) == [18, 19, 21]


def test_commanded_displacement_is_projected_into_the_image():
    K = np.array([[F_PX, 0, 16], [0, F_PX, 16], [0, 0, 1]])
    du, dv = commanded_px({"commanded_displacement_world_m": [0.25, -0.125, 0.0]}, np.array([0.0, 0.0, 1.0]), K, np.eye(4))
    assert du == pytest.approx(8.0) and dv == pytest.approx(-4.0)
    # Farther away, the same displacement is smaller in the image.
    du2, _ = commanded_px({"commanded_displacement_world_m": [0.25, 0, 0]}, np.array([0.0, 0.0, 2.0]), K, np.eye(4))
    assert du2 == pytest.approx(4.0)


def _group_entries(pred_of):
    rows = []
    for k in range(len(GROUP)):
        ep = group_episode(k)
        rows.append((ep, episode_believability(ep, "close", pred_of(ep), patch_px=4)))
    return rows


def test_ground_truth_predictions_score_full_contrast_and_presence():
    rows = _group_entries(lambda ep: ep.cameras["close"].rgb)
    for ep, b in rows:
        assert b["metrics"]["objects_present"] == 1.0
        assert set(b["per_object"]) == {"red_cube", "green_cube"}
        assert b["metrics"]["edge_sharpness"] == pytest.approx(1.0)
    contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in rows])
    assert contrast["groups"] == 1 and contrast["instructions"] == 3
    assert contrast["share"] == 1.0
    pushes = [r for r in contrast["per_group"]["Synthetic-v0/seed_100000"] if not r["still"]]
    assert all(r["cosine"] > 0.99 for r in pushes)
    assert pushes[0]["commanded_px"] == pytest.approx([16.0, 0.0])


def test_static_world_keeps_still_objects_but_follows_only_keep_still():
    rows = _group_entries(lambda ep: static(ep.cameras["close"].rgb))
    by_skill = {ep.intent["skill"] + str(ep.variant): b for ep, b in rows}
    assert by_skill["keep_still2"]["metrics"]["objects_present"] == 1.0
    for key in ("push0", "push1"):
        b = by_skill[key]
        # The still object is always there; the moved one leaves its first place.
        moved = GROUP[int(key[-1])][2]
        still = "green_cube" if moved == "red_cube" else "red_cube"
        assert b["per_object"][still] == 1.0 and b["per_object"][moved] <= 0.5
        assert b["metrics"]["objects_present"] <= 0.5
        assert b["metrics"]["motion"] == 0.0
    contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in rows])
    assert contrast["share"] == pytest.approx(1 / 3)
    assert contrast["per_skill"] == {"keep_still": 1.0, "push": 0.0}


def test_wrong_object_and_restless_keep_still_are_wrong():
    gt = {k: group_episode(k).cameras["close"].rgb for k in range(3)}
    # Every instruction gets the clip that pushes the red cube: right only for "push the red cube".
    rows = _group_entries(lambda ep: gt[0])
    contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in rows])
    assert [r["right"] for r in contrast["per_group"]["Synthetic-v0/seed_100000"]] == [True, False, False]


def test_version1_episode_has_no_contrast_entry_and_gripper_skills_are_left_out():
    ep = group_episode(0)
    ep.intent = None
    assert contrast_entry(ep, "close", ep.cameras["close"].rgb) is None
    ep = group_episode(0)
    ep.intent = dict(ep.intent, skill="hover")
    assert contrast_entry(ep, "close", ep.cameras["close"].rgb) is None
    assert clip_motion(ep.cameras["close"].rgb[:1]) == 0.0


def test_breakdown_per_skill_and_task():
    rows = [{"task": "A", "skill": "push", "metrics": {"m": {"x": 1.0}}},
            {"task": "A", "skill": "keep_still", "metrics": {"m": {"x": 3.0}}},
            {"task": "B", "skill": "push", "metrics": {"m": {"x": float("nan")}}}]
    assert breakdown(rows, ["m"], "skill") == {"keep_still": {"m": {"x": 3.0}}, "push": {"m": {"x": 1.0}}}
    assert breakdown(rows, ["m"], "task")["A"]["m"]["x"] == 2.0


@pytest.fixture(scope="module")
def two_checkpoints(micro_preset, tmp_path_factory):
    from model_fixtures import MICRO
    from synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.trainer import Trainer, TrainConfig

    root = tmp_path_factory.mktemp("believe")
    data = write_synthetic_dataset(root / "train", episodes=2)
    a = Trainer(TrainConfig(data=data, out=root / "run", preset=MICRO.name, max_steps=4, val_every=0,
                            ckpt_every=0, progress=False)).train()
    b = root / "other" / "v2"
    shutil.copytree(a, b)
    heldout = root / "heldout"
    df.init_dataset(heldout, df.DatasetInfo(height=SIZE, width=SIZE, cameras=["close"]))
    for k in range(len(GROUP)):
        df.write_episode(heldout, group_episode(k))
    return a, b, heldout


def test_evaluate_scores_several_checkpoints_side_by_side(two_checkpoints, tmp_path):
    from tesseract4d import cli

    a, b, heldout = two_checkpoints
    out = tmp_path / "eval"
    assert cli.main(["evaluate", "--heldout", str(heldout), "--checkpoint", str(a), "--checkpoint", str(b),
                     "--out", str(out), "--steps", "2"]) == 0
    report = json.loads((out / "report.json").read_text())
    names = [a.name, "v2"]
    assert list(report["methods"]) == [names[0], names[0] + "_raw", "v2", "v2_raw", "static"]
    assert report["checkpoints"] == {names[0]: str(a), "v2": str(b)}
    for m in report["methods"]:
        for key in ("rgb_psnr_db_moving", "objects_present", "token_grid_ratio", "edge_sharpness", "contrast"):
            assert key in report["summary"][m]
        assert set(report["per_skill"]) == {"push", "keep_still"} and m in report["per_skill"]["push"]
        assert m in report["per_task"]["Synthetic-v0"]
    # The static world follows only "keep still"; the ground truth follows all.
    assert report["summary"]["static"]["contrast"] == pytest.approx(1 / 3)
    assert report["contrast"]["ground_truth"]["share"] == 1.0
    assert report["contrast"]["static"]["per_skill"] == {"keep_still": 1.0, "push": 0.0}
    assert report["contrast"]["static"]["per_task"] == {"Synthetic-v0": pytest.approx(1 / 3)}
    md = (out / "report.md").read_text()
    for label in report["methods"].values():
        assert label in md
    assert "object permanence" in md and "instruction contrast" in md and "✗" in md and "per skill" in md
    assert "| keep_still | 1 |" in md and "| Synthetic-v0 | 3 |" in md


def test_single_checkpoint_keeps_the_report_keys(two_checkpoints):
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, format_markdown

    a, _, heldout = two_checkpoints
    report = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2), progress=False)
    assert list(report["methods"]) == ["model", "model_raw", "static"]
    assert {"model", "model_raw", "static"} <= set(report["summary"]) and "model" in report["instruction_following"]
    assert "model + consistency" in format_markdown(report)


def test_a_shaded_object_is_tracked_and_found_by_its_own_colours():
    from tesseract4d.evaluation.believability import objects_present
    from tesseract4d.evaluation.heldout_believability import track_object
    from tesseract4d.evaluation.instruction_following import track_colour

    # A cube with a lit top and a dark side on a grey table: its mean colour matches none of its pixels.
    rgb = np.full((2, 32, 32, 3), 100, np.uint8)
    seg = np.zeros((2, 32, 32), np.int32)
    for t, u0 in enumerate((8, 14)):
        rgb[t, 10:14, u0:u0 + 8] = (240, 240, 60)
        rgb[t, 14:18, u0:u0 + 8] = (90, 90, 20)
        seg[t, 10:18, u0:u0 + 8] = 1
    assert track_colour(rgb[0], seg[0] == 1, rgb[1]) is None  # the mean-colour tracker loses it
    du, dv = track_object(rgb[0], seg[0] == 1, rgb[1])
    assert du == pytest.approx(6.0) and dv == pytest.approx(0.0)
    assert track_object(rgb[0], seg[0] == 1, rgb[0]) == (0.0, 0.0)
    assert objects_present(rgb, seg, [1], rgb).frames_all_present == 1.0
    table_only = np.full_like(rgb, 100)
    assert objects_present(rgb, seg, [1], table_only).frames_all_present == 0.0


@pytest.mark.sim
def test_ground_truth_of_a_simulated_group_is_believed(tmp_path):
    """On a rendered tabletop group (shaded cubes, the arm occluding them) the ground truth keeps
    every object and follows every instruction; the static world follows only "keep still"."""
    from tesseract4d import cli

    out = tmp_path / "groups"
    assert cli.main(["datagen", "--tasks", "Tesseract4dTabletop-v1", "--instructions-per-scene", "2", "--skills",
                     "push_left,keep_still", "--episodes", "1", "--seed-start", "100000", "--instruction-split",
                     "heldout", "--resolution", "64", "--frames", "8", "--out", str(out), "--no-previews",
                     "--quiet"]) == 0
    gt_entries, static_entries = [], []
    for path in df.list_episode_files(out):
        ep = df.read_episode(path)
        rgb = ep.cameras["close"].rgb
        truth = episode_believability(ep, "close", rgb, patch_px=4)
        still = episode_believability(ep, "close", static(rgb), patch_px=4)
        assert truth["metrics"]["objects_present"] == 1.0 and len(truth["per_object"]) >= 2
        assert 0.8 < truth["metrics"]["token_grid_ratio"] < 1.25
        if ep.intent["skill"] == "keep_still":
            assert still["metrics"]["objects_present"] == 1.0
        gt_entries.append((ep.group_id, truth["contrast_entry"]))
        static_entries.append((ep.group_id, still["contrast_entry"]))
    assert contrast_by_group(gt_entries)["share"] == 1.0
    assert contrast_by_group(static_entries)["per_skill"] == {"keep_still": 1.0, "push": 0.0}


def test_checkpoint_option_defaults_to_the_shipped_model_and_repeats():
    import argparse

    from tesseract4d.cli import evaluate
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT

    parser = argparse.ArgumentParser()
    evaluate.add_arguments(parser)
    assert parser.parse_args(["--heldout", "d"]).checkpoint == SHIPPED_CHECKPOINT
    assert parser.parse_args(["--heldout", "d", "--checkpoint", "a"]).checkpoint == [Path("a")]
    assert parser.parse_args(["--heldout", "d", "--checkpoint", "a", "--checkpoint", "b"]).checkpoint == [Path("a"), Path("b")]


def test_direction_breakdown_per_task():
    from tesseract4d.evaluation.heldout_believability import direction_breakdown

    d = lambda cos, valid=True: {"cosine": cos, "valid": valid}  # noqa: E731
    rows = [{"task": "PushCube-v1", "skill": "task", "direction": {"m": d(0.9)}},
            {"task": "PushCube-v1", "skill": "task", "direction": {"m": d(-0.2)}},
            {"task": "PushCube-v1", "skill": "task", "direction": {"m": d(0.0, valid=False)}},
            {"task": "Other-v1", "skill": "task", "direction": {}}]
    out = direction_breakdown(rows, ["m"], "task")
    assert out == {"PushCube-v1": {"m": {"episodes": 2, "right_way": 0.5, "mean_cosine": pytest.approx(0.35)}}}
