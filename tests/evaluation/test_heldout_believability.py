"""Believability measures in the held-out evaluation: synthetic counterfactual groups with known
motion (no simulator), scored as the ground truth, as the static world, and by two checkpoints
side by side."""

from __future__ import annotations

import copy

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from tesseract4d.testing.synthetic_scene import GROUP, group_episode
from tesseract4d.testing.synthetic_scene import GROUP_F_PX as F_PX
from tesseract4d.testing.synthetic_scene import GROUP_FRAMES as FRAMES
from tesseract4d.testing.synthetic_scene import GROUP_SIZE as SIZE

from tesseract4d import dataset_format as df
from tesseract4d.evaluation.heldout_believability import (breakdown, clip_motion, commanded_px, contrast_by_group,
                                                          contrast_entry, episode_believability)


def static(rgb: np.ndarray) -> np.ndarray:
    return np.repeat(rgb[:1], len(rgb), axis=0)


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
    assert (contrast["still_right"], contrast["still_instructions"]) == (1, 1)
    # Its third comes from "keep still" alone: none of the active instructions is right.
    assert (contrast["active_right"], contrast["active_instructions"]) == (0, 2)
    # 1 of 3 right: Wilson 95 % (0.0615, 0.7923) (tests/contracts/test_intervals.py has the formula worked by hand)
    assert contrast["wilson95"] == pytest.approx([0.0615, 0.7923], abs=1e-4)


def _red_push_ending_as(paint):
    """Predictions of the group: the ground truth, except that the red-cube push's last frame shows
    the red cube as ``paint(frame)`` draws it on the ground truth's background."""
    def pred_of(ep):
        rgb = ep.cameras["close"].rgb.copy()
        if ep.intent["target"] == "red_cube":
            rgb[-1][ep.cameras["close"].segmentation[-1] == 18] = 60  # erase it (a grey of the plane)
            paint(rgb[-1])
        return rgb
    return pred_of


def test_a_smear_or_a_copy_moves_the_centroid_right_but_is_not_found_whole():
    """The red cube (8 px, pushed 16 px right) drawn as a streak along its path, or twice (at its start
    and its goal): the tracked centroid moves right (cos 1: "right"), but the object is not found whole.
    The ground truth itself is found whole."""
    from tesseract4d.evaluation.heldout_believability import find_object

    truth = group_episode(0).cameras["close"]
    found = find_object(truth.rgb[0], truth.segmentation[0] == 18, truth.rgb[-1])
    assert found.whole and found.du == pytest.approx(16.0) and found.pixels_share == pytest.approx(1.0)
    assert found.spread_ratio == pytest.approx(1.0)

    def streak(frame):
        frame[10:18, 6:30] = (220, 30, 30)

    def copy(frame):
        frame[10:18, 6:14] = (220, 30, 30)
        frame[10:18, 22:30] = (220, 30, 30)

    def faded(frame):  # a quarter of it left, where it should be
        frame[10:12, 22:26] = (220, 30, 30)

    for paint in (streak, copy, faded):
        rows = _group_entries(_red_push_ending_as(paint))
        contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in rows])
        red = contrast["per_group"]["Synthetic-v0/seed_100000"][0]
        assert red["right"] and not red["whole"] and not red["right_whole"], paint.__name__
        assert (contrast["right"], contrast["right_whole"]) == (3, 2), paint.__name__
        assert contrast["share_whole"] == pytest.approx(2 / 3)
    truth_rows = _group_entries(lambda ep: ep.cameras["close"].rgb)
    contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in truth_rows])
    assert contrast["right_whole"] == contrast["right"] == 3  # "keep still" counts as judged


def test_wrong_object_and_restless_keep_still_are_wrong():
    gt = {k: group_episode(k).cameras["close"].rgb for k in range(3)}
    # Every instruction gets the clip that pushes the red cube: right only for "push the red cube".
    rows = _group_entries(lambda ep: gt[0])
    contrast = contrast_by_group([(ep.group_id, b["contrast_entry"]) for ep, b in rows])
    assert [r["right"] for r in contrast["per_group"]["Synthetic-v0/seed_100000"]] == [True, False, False]
    assert (contrast["still_right"], contrast["still_instructions"]) == (0, 1)
    assert (contrast["active_right"], contrast["active_instructions"]) == (1, 2)


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
    from tesseract4d.testing.model_fixtures import MICRO
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.trainer import Trainer, TrainConfig

    root = tmp_path_factory.mktemp("believe")
    data = write_synthetic_dataset(root / "train", episodes=2)
    a = Trainer(TrainConfig(data=data, out=root / "run", preset=MICRO.name, max_steps=4, val_every=0,
                            ckpt_every=0, quiet=True)).train()
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
        for key in ("rgb_psnr_db_moving", "objects_present", "token_grid_ratio", "edge_sharpness", "contrast",
                    "contrast_whole"):
            assert key in report["summary"][m]
        assert set(report["per_skill"]) == {"push", "keep_still"} and m in report["per_skill"]["push"]
        assert m in report["per_task"]["Synthetic-v0"]
    # The static world follows only "keep still"; the ground truth follows all.
    assert report["summary"]["static"]["contrast"] == pytest.approx(1 / 3)
    assert report["contrast"]["ground_truth"]["share"] == report["contrast"]["ground_truth"]["share_whole"] == 1.0
    assert report["format_version"] == 11 and "arm_judged" in report["contrast"]["ground_truth"]
    # One network per checkpoint, one judgment per episode of the group (three distinct instructions).
    disc = report["discrimination"][names[0]]
    assert disc == report["discrimination"][names[0] + "_raw"] and disc["episodes"] == 3
    assert disc["chance"] == pytest.approx(1 / 3) and "static" not in report["discrimination"]
    words = disc["words_over_sample"]
    assert words["pairs"] == 3 * 2 and 0 <= words["words"] <= words["pairs"] and words["t"] == 0.5
    # Where permanence is lost: the static world keeps every object that stays put, and the instructed one
    # only in the frames before it has moved away from where it stood.
    static = report["summary"]["static"]
    assert static["objects_present_others"] == 1.0 and 0 < static["objects_present_instructed"] < 1
    assert {r["target"] for r in report["rows"]} == {"red_cube", "green_cube", None}
    assert report["contrast"]["static"]["per_skill"] == {"keep_still": 1.0, "push": 0.0}
    assert report["contrast"]["static"]["per_task"] == {"Synthetic-v0": pytest.approx(1 / 3)}
    md = (out / "report.md").read_text()
    _tables_hold_their_columns(md)
    for label in report["methods"].values():
        assert label in md
    assert "object permanence" in md and "instruction contrast" in md and "✗" in md and "per skill" in md
    assert "the moved object found whole" in md and "instruction discrimination" in md
    assert "frames with the instructed object, per object" in md and "frames with each other object" in md
    assert "words over the noisy sample" in md
    assert "| keep_still | 1 |" in md and "| Synthetic-v0 | 3 |" in md


@pytest.mark.slow
def test_several_noise_seeds_pool_the_single_seed_scores(two_checkpoints, tmp_path):
    """`--sample-seed 0 1` scores one row per episode and seed: its means are the means of the two
    single-seed runs, its contrast counts are their sums, and the static world is the same in both."""
    from tesseract4d import cli
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout

    a, _, heldout = two_checkpoints
    single = [evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2, precision="fp32", sample_seed=s),
                               progress=False) for s in (0, 1)]
    out = tmp_path / "seeds"
    assert cli.main(["evaluate", "--heldout", str(heldout), "--checkpoint", str(a), "--steps", "2", "--set", "precision=fp32",
                     "--sample-seed", "0", "1", "--out", str(out)]) == 0
    both = json.loads((out / "report.json").read_text())
    assert both["episodes"] == single[0]["episodes"] == len(GROUP) and both["sample_seeds"] == [0, 1]
    assert [r["sample_seed"] for r in both["rows"]] == [0, 1] * len(GROUP)
    assert both["episodes_per_skill"] == single[0]["episodes_per_skill"]
    for key, value in both["summary"]["model_raw"].items():
        one, two = (r["summary"]["model_raw"][key] for r in single)
        if value is not None and one is not None and two is not None:
            assert value == pytest.approx((one + two) / 2, rel=1e-6, abs=1e-9), key
    for m in ("model", "model_raw", "static", "ground_truth"):
        assert both["contrast"][m]["instructions"] == sum(r["contrast"][m]["instructions"] for r in single)
        assert both["contrast"][m]["right"] == sum(r["contrast"][m]["right"] for r in single)
        assert both["contrast"][m]["right_whole"] == sum(r["contrast"][m]["right_whole"] for r in single)
    assert both["contrast"]["static"]["groups"] == 2 * single[0]["contrast"]["static"]["groups"]
    for r0, r1 in zip(both["rows"][0::2], both["rows"][1::2]):
        assert r0["episode"] == r1["episode"] and r0["metrics"]["static"] == r1["metrics"]["static"]
    md = (out / "report.md").read_text()
    assert "2 noise seeds" in md and f"{len(GROUP)} instructions in 1 groups" in md
    # Seeds must be distinct.
    assert cli.main(["evaluate", "--heldout", str(heldout), "--checkpoint", str(a), "--sample-seed", "1", "1"]) == 2


@pytest.mark.slow
def test_each_checkpoint_samples_with_its_own_steps(two_checkpoints, tmp_path):
    # A 2-step student listed before its 10-step teacher: each keeps its own sampler, so the teacher
    # scores exactly as it does alone (up to 1e-6: rounding of the batched maths).
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout

    a, _, heldout = two_checkpoints
    student = tmp_path / "student"
    shutil.copytree(a, student)
    config = json.loads((student / "tesseract4d_config.json").read_text())
    teacher_steps = config["preset"]["num_steps"]
    config["preset"]["num_steps"] = 2
    config["preset"]["text_guidance"] = 1.0
    (student / "tesseract4d_config.json").write_text(json.dumps(config))
    both = evaluate_heldout(HeldoutConfig(checkpoint=[student, a], data=heldout), progress=False)
    alone = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout), progress=False)
    assert teacher_steps != 2
    assert both["sampler"] == {"student": {"num_steps": 2, "text_guidance": 1.0},
                               a.name: {"num_steps": teacher_steps, "text_guidance": alone["sampler"]["model"]["text_guidance"]}}
    for key in ("rgb_psnr_db_moving", "depth_abs_rel_moving", "chamfer_l1_m_moving"):
        assert both["summary"][a.name][key] == pytest.approx(alone["summary"]["model"][key], rel=1e-6, abs=1e-6), key
    assert both["summary"]["student"]["rgb_psnr_db"] != both["summary"][a.name]["rgb_psnr_db"]
    # --steps still sets every checkpoint's steps.
    forced = evaluate_heldout(HeldoutConfig(checkpoint=[student, a], data=heldout, num_steps=3), progress=False)
    assert {v["num_steps"] for v in forced["sampler"].values()} == {3}


def test_a_guidance_interval_is_sampled_and_reported(two_checkpoints, tmp_path):
    """A checkpoint guided only at high noise (set-sampler --guidance-min-sigma) is evaluated with its
    interval, and the report names it."""
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, format_markdown
    from tesseract4d.model.checkpoint_copies import write_sampler_copy

    a, _, heldout = two_checkpoints
    guided = write_sampler_copy(a, tmp_path / "guided", {"text_guidance": 2.0})
    interval = write_sampler_copy(a, tmp_path / "interval", {"text_guidance": 2.0, "guidance_min_sigma": 0.5})
    report = evaluate_heldout(HeldoutConfig(checkpoint=[guided, interval], data=heldout), progress=False)
    steps = report["sampler"]["guided"]["num_steps"]
    assert report["sampler"] == {"guided": {"num_steps": steps, "text_guidance": 2.0},
                                 "interval": {"num_steps": steps, "text_guidance": 2.0, "guidance_min_sigma": 0.5}}
    assert report["summary"]["guided"]["rgb_psnr_db"] != report["summary"]["interval"]["rgb_psnr_db"]
    assert "interval 10 steps, text guidance 2 at noise ≥ 0.5".replace("10", str(steps)) in format_markdown(report)
    from tesseract4d.evaluation.heldout import describe_sampler

    assert describe_sampler({"num_steps": 2, "text_guidance": 1.0, "static_tolerance": 0.2}) == (
        "2 steps, text guidance 1, first frame kept where still (tolerance 0.2)")
    assert describe_sampler({"num_steps": 2, "text_guidance": 1.0, "draws": 4}) == (
        "2 steps, text guidance 1, the best of 4 noise draws")


def test_a_sampler_started_from_a_clip_begins_at_its_noise_level_and_runs_only_the_steps_from_there(two_checkpoints):
    """The pipeline's ``start`` diagnostic: at noise 1 the clip is the one pure noise gives, exactly; at
    0.5 of 4 steps (levels 1, 0.667, 0.334, 0.001) the network is first shown (1 - 0.334) clip + 0.334
    noise and runs 2 passes, not 4."""
    import torch

    from tesseract4d.model.predict import load_pipeline

    a, _, _ = two_checkpoints
    pipe = load_pipeline(a, precision="fp32")
    first = torch.rand(1, 7, *pipe.resolution) * 2 - 1
    noise = torch.randn(pipe.latent_shape(1), generator=torch.Generator().manual_seed(1))
    clean = torch.randn(pipe.latent_shape(1), generator=torch.Generator().manual_seed(2))
    plain = pipe(first, ["push the cube"], num_inference_steps=4, latents=noise, output_type="latent")
    at_one = pipe(first, ["push the cube"], num_inference_steps=4, latents=noise, output_type="latent", start=(clean, 1.0))
    assert torch.equal(plain, at_one)
    inputs = []
    hook = pipe.transformer.register_forward_pre_hook(lambda module, args: inputs.append(args[0][:1].clone()))
    try:
        pipe(first, ["push the cube"], num_inference_steps=4, latents=noise, output_type="latent", start=(clean, 0.5))
    finally:
        hook.remove()
    level = float(pipe.scheduler.sigmas[2])
    assert abs(level - 0.334) < 1e-3 and len(inputs) == 2
    assert torch.allclose(inputs[0], (1 - level) * clean + level * noise, atol=1e-6)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="noise level"):
            pipe(first, ["push the cube"], num_inference_steps=4, latents=noise, start=(clean, bad))


def test_start_from_truth_is_sampled_and_reported_and_refused_out_of_range(two_checkpoints, tmp_path):
    """``evaluate --heldout --start-from-truth``: at 1 the scores are those of the plain run, the report
    names the diagnostic in its sampler; a level outside (0, 1] is a one-line refusal."""
    from tesseract4d.errors import UserError
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, format_markdown

    a, _, heldout = two_checkpoints
    plain = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2), progress=False)
    at_one = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2, start_from_truth=1.0), progress=False)
    assert at_one["summary"]["model_raw"] == plain["summary"]["model_raw"]
    assert at_one["sampler"]["model"]["start_from_truth"] == 1.0 and "start_from_truth" not in plain["sampler"]["model"]
    near = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=4, start_from_truth=0.4), progress=False)
    assert near["summary"]["model_raw"] != plain["summary"]["model_raw"]
    assert "started from the true future at noise ≤ 0.4" in format_markdown(near)
    for bad in (0.0, -0.5, 2.0):
        with pytest.raises(UserError, match="--start-from-truth") as err:
            evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2, start_from_truth=bad), progress=False)
        assert "\n" not in str(err.value)


def test_single_checkpoint_keeps_the_report_keys(two_checkpoints):
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, format_markdown

    a, _, heldout = two_checkpoints
    report = evaluate_heldout(HeldoutConfig(checkpoint=a, data=heldout, num_steps=2), progress=False)
    assert list(report["methods"]) == ["model", "model_raw", "static"]
    assert {"model", "model_raw", "static"} <= set(report["summary"]) and "model" in report["instruction_following"]
    md = format_markdown(report)
    assert "model + consistency" in md
    ci = report["contrast"]["model"]["wilson95"]
    assert f"({ci[0]:.2f}–{ci[1]:.2f})" in md and '"keep still" right' in md
    assert "active instructions right" in md
    _tables_hold_their_columns(md)
    # A set without a "keep still" instruction still shows its active instructions' row.
    without_still = copy.deepcopy(report)
    for c in without_still["contrast"].values():
        c.pop("still_instructions", None), c.pop("still_right", None)
    md = format_markdown(without_still)
    assert '"keep still" right' not in md and "active instructions right" in md


def _tables_hold_their_columns(md: str) -> None:
    """Every row of every Markdown table has its header's number of cells (a "|" inside a cell
    would split it)."""
    table = []
    for line in md.splitlines() + [""]:
        if line.startswith("|"):
            table.append(line)
            continue
        if table:
            counts = {len(row.strip().strip("|").split("|")) for row in table}
            assert len(counts) == 1, table
        table = []


@pytest.fixture(scope="module")
def checkpoint_64(micro_preset, tmp_path_factory):
    """A micro checkpoint at 64x64 (twice the group episodes' 32x32) and the groups seen at 64x64."""
    from tesseract4d.testing.model_fixtures import MICRO
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.presets import PRESETS
    from tesseract4d.model.trainer import Trainer, TrainConfig

    preset = dataclasses.replace(MICRO, name="micro-64", height=2 * SIZE, width=2 * SIZE,
                                 backbone=dict(MICRO.backbone, sample_width=2 * SIZE, sample_height=2 * SIZE))
    root = tmp_path_factory.mktemp("believe64")
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(PRESETS, preset.name, preset)
        data = write_synthetic_dataset(root / "train", episodes=2, size=2 * SIZE)
        run = Trainer(TrainConfig(data=data, out=root / "run", preset=preset.name, max_steps=2, val_every=0,
                                  ckpt_every=0, quiet=True)).train()
        ckpt = root / "v2"
        shutil.copytree(run, ckpt)
        heldout = root / "heldout64"
        df.init_dataset(heldout, df.DatasetInfo(height=2 * SIZE, width=2 * SIZE, cameras=["close"]))
        for k in range(len(GROUP)):
            df.write_episode(heldout, group_episode(k, scale=2))
        yield ckpt, heldout


def _finite(report: dict, method: str) -> None:
    summary = report["summary"][method]
    for key in ("rgb_psnr_db", "rgb_psnr_db_moving", "depth_abs_rel", "normal_mean_deg", "chamfer_l1_m",
                "chamfer_l1_m_moving", "objects_present", "token_grid_ratio", "edge_sharpness", "contrast"):
        assert summary[key] is not None and np.isfinite(summary[key]), (method, key, summary[key])


@pytest.mark.slow
def test_checkpoints_of_two_resolutions_are_scored_on_one_heldout_set(two_checkpoints, checkpoint_64, tmp_path):
    """A 32x32 model beside a 64x64 one on 64x64 data: the 32x32 prediction is upsampled, every metric
    is taken at 64x64 against the untouched ground truth, and the report says so."""
    from tesseract4d import cli

    a, _, _ = two_checkpoints
    v2, heldout64 = checkpoint_64
    out = tmp_path / "eval"
    assert cli.main(["evaluate", "--heldout", str(heldout64), "--checkpoint", str(a), "--checkpoint", str(v2),
                     "--out", str(out), "--steps", "2", "--set", "precision=fp32"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["resolutions"] == {a.name: {"model": [SIZE, SIZE], "data": [2 * SIZE, 2 * SIZE], "resized": "upsampled"},
                                     "v2": {"model": [2 * SIZE, 2 * SIZE], "data": [2 * SIZE, 2 * SIZE], "resized": None}}
    assert report["methods"][a.name] == f"{a.name} (32×32, upsampled to 64×64) + consistency"
    assert report["methods"]["v2"] == "v2 + consistency"
    for m in report["methods"]:
        _finite(report, m)
    md = (out / "report.md").read_text()
    assert f"{a.name} (32×32, upsampled to 64×64), no consistency" in md and "Resolutions: " in md


def test_a_model_above_the_data_resolution_is_downsampled(two_checkpoints, checkpoint_64):
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout

    _, _, heldout32 = two_checkpoints
    v2, _ = checkpoint_64
    report = evaluate_heldout(HeldoutConfig(checkpoint=v2, data=heldout32, num_steps=2, precision="fp32"),
                              progress=False)
    assert report["resolutions"]["model"]["resized"] == "downsampled"
    assert report["methods"]["model_raw"] == "model (64×64, downsampled to 32×32), no consistency"
    for m in report["methods"]:
        _finite(report, m)


def test_a_prediction_comes_back_at_the_data_resolution_from_the_data_first_frame(two_checkpoints, checkpoint_64):
    """The 32x32 model on a 64x64 first frame: the prediction is 64x64 with the data's K and its
    frame 0 is the data's first frame; the RGB as the model made it (for the token grid) is 32x32."""
    from tesseract4d.evaluation.heldout import predict_at_data_resolution
    from tesseract4d.model.predict import load_pipeline

    a, _, _ = two_checkpoints
    _, heldout64 = checkpoint_64
    path = df.list_episode_files(heldout64)[0]
    first = df.read_episode(path, cameras=["close"], frames=slice(0, 1))
    [(pred, model_rgb)] = predict_at_data_resolution(load_pipeline(a, precision="fp32"), [first], ["push"], ["close"],
                                                     [FRAMES], seed=0, num_steps=2, batch_size=None)
    cam, cam0 = pred.cameras["close"], first.cameras["close"]
    assert cam.rgb.shape == (FRAMES, 2 * SIZE, 2 * SIZE, 3) and model_rgb.shape == (FRAMES, SIZE, SIZE, 3)
    assert cam.depth_m.shape == (FRAMES, 2 * SIZE, 2 * SIZE) and cam.normal_cam.shape == (FRAMES, 2 * SIZE, 2 * SIZE, 3)
    np.testing.assert_allclose(cam.K, np.repeat(cam0.K[:1], FRAMES, 0))
    assert np.array_equal(cam.rgb[0], cam0.rgb[0]) and np.array_equal(cam.depth_m[0], cam0.depth_m[0])
    length = np.linalg.norm(cam.normal_cam, axis=-1)
    assert np.all((np.abs(length - 1) < 1e-3) | (length == 0))
    assert pred.metadata["prediction"]["resized"] == {"model_resolution": [SIZE, SIZE],
                                                      "data_resolution": [2 * SIZE, 2 * SIZE]}


def test_every_scene_draws_its_own_noise_and_a_group_shares_it():
    from tesseract4d.evaluation.heldout import scene_noise_seed

    group = scene_noise_seed(0, "Tesseract4dTabletop-v1", 100000)
    assert group == scene_noise_seed(0, "Tesseract4dTabletop-v1", 100000)  # every instruction of the group
    others = {scene_noise_seed(0, "Tesseract4dTabletop-v1", 100001), scene_noise_seed(0, "PushCube-v1", 100000),
              scene_noise_seed(1, "Tesseract4dTabletop-v1", 100000)}
    assert group not in others and len(others) == 3
    seeds = {scene_noise_seed(s, env, k) for s in range(3) for env in ("PushCube-v1", "PullCube-v1") for k in range(100)}
    assert len(seeds) == 600 and all(0 <= x < 1 << 62 for x in seeds)


def test_same_resolution_is_predicted_as_one_scene_at_a_time_and_batching_changes_nothing(two_checkpoints):
    """At the data's resolution nothing is resized: with one scene per call the raw model scores
    exactly what predict_episode's prediction with the scene's noise seed scores (what the evaluation
    did one episode at a time); several scenes per call give the same numbers up to the rounding of
    batched fp32 maths."""
    from tesseract4d.evaluation.episode import evaluate_episode
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, scene_noise_seed, select_episodes
    from tesseract4d.evaluation.metrics import moving_region_mask
    from tesseract4d.model.predict import load_pipeline, predict_episode

    a, _, heldout = two_checkpoints
    cfg = HeldoutConfig(checkpoint=a, data=heldout, num_steps=2, precision="fp32", sample_seed=3)
    one = evaluate_heldout(dataclasses.replace(cfg, batch_size=1), progress=False)
    batched = evaluate_heldout(dataclasses.replace(cfg, batch_size=2), progress=False)
    assert one["resolutions"]["model"]["resized"] is None and one["methods"]["model"] == "model + consistency"
    pipe = load_pipeline(a, precision="fp32")
    for path, row in zip(select_episodes(heldout, None), one["rows"]):
        gt = df.read_episode(path)
        first = df.read_episode(path, cameras=["close"], frames=slice(0, 1))
        pred = predict_episode(pipe, first, gt.instruction, num_frames=FRAMES, num_steps=2,
                               seed=scene_noise_seed(3, gt.env_id, gt.seed))
        alone = evaluate_episode(pred, gt, camera="close", moving_mask=moving_region_mask(gt.cameras["close"]),
                                 max_depth_m=one["max_depth_m"])["mean"]
        for key, value in alone.items():
            assert row["metrics"]["model_raw"][key] == value or (np.isnan(value) and row["metrics"]["model_raw"][key] is None), key
    for r1, r2 in zip(one["rows"], batched["rows"]):
        for method, metrics in r1["metrics"].items():
            for key, value in metrics.items():
                other = r2["metrics"][method][key]
                assert (value is None and other is None) or value == pytest.approx(other, rel=1e-4, abs=1e-6), (method, key)


def test_a_resolution_evaluation_cannot_resize_to_is_a_one_line_error(two_checkpoints, tmp_path):
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.errors import UserError
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout

    a, _, _ = two_checkpoints
    data = write_synthetic_dataset(tmp_path / "heldout48", episodes=1, size=48)
    with pytest.raises(UserError, match=r"predicts 32x32 frames but .* holds 48x48") as err:
        evaluate_heldout(HeldoutConfig(checkpoint=a, data=data, num_steps=2), progress=False)
    assert "\n" not in str(err.value) and "--resolution 32" in str(err.value)


def test_token_size_in_data_pixels_and_resolution_notes():
    from fractions import Fraction

    from tesseract4d.evaluation.heldout import resolution_note, token_px_in_data

    assert token_px_in_data(4, Fraction(1, 2)) == 8 and token_px_in_data(8, Fraction(2)) == 4
    assert token_px_in_data(4, Fraction(4)) is None and token_px_in_data(4, Fraction(2)) == 2
    assert resolution_note((64, 64), (64, 64)) == ""
    assert resolution_note((64, 64), (128, 128)) == " (64×64, upsampled to 128×128)"
    assert resolution_note((128, 128), (64, 64)) == " (128×128, downsampled to 64×64)"


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
                     "heldout", "--resolution", "64", "--frames", "8", "--out", str(out), "--set", "previews=false",
                     "--quiet"]) == 0
    gt_entries, static_entries = [], []
    for path in df.list_episode_files(out):
        ep = df.read_episode(path)
        rgb = ep.cameras["close"].rgb
        depth = ep.cameras["close"].depth_m
        truth = episode_believability(ep, "close", rgb, patch_px=4, pred_depth_m=depth)
        still = episode_believability(ep, "close", static(rgb), patch_px=4, pred_depth_m=static(depth))
        assert truth["metrics"]["objects_present"] == 1.0 and len(truth["per_object"]) >= 2
        assert 0.8 < truth["metrics"]["token_grid_ratio"] < 1.25
        if ep.intent["skill"] == "keep_still":
            assert still["metrics"]["objects_present"] == 1.0
        gt_entries.append((ep.group_id, truth["contrast_entry"]))
        static_entries.append((ep.group_id, still["contrast_entry"]))
    assert contrast_by_group(gt_entries)["share"] == contrast_by_group(gt_entries)["share_whole"] == 1.0
    assert contrast_by_group(static_entries)["per_skill"] == {"keep_still": 1.0, "push": 0.0}
    # The truth's arm goes to the pushed object; the static world's goes nowhere.
    truth_arm, still_arm = contrast_by_group(gt_entries), contrast_by_group(static_entries)
    assert truth_arm["arm_judged"] == truth_arm["arm_instructed"] == truth_arm["arm_measured"] == 1
    assert (still_arm["arm_judged"], still_arm["arm_instructed"]) == (1, 0)


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


def test_the_tracker_window_covers_the_same_share_of_the_image_at_any_resolution():
    """A cube that moves 40 px in a 128 px image (20 px at 64) is found at both sizes."""
    from tesseract4d.evaluation.heldout_believability import track_object

    for size, shift in ((64, 20), (128, 40)):
        first = np.full((size, size, 3), 90, np.uint8)
        target = first.copy()
        s = size // 8
        first[s:2 * s, s:2 * s] = (200, 30, 30)
        target[s:2 * s, s + shift:2 * s + shift] = (200, 30, 30)
        mask = np.zeros((size, size), bool)
        mask[s:2 * s, s:2 * s] = True
        du, dv = track_object(first, mask, target)
        assert du == pytest.approx(shift) and dv == pytest.approx(0.0), size


def test_clip_motion_ignores_a_constant_offset_of_the_predicted_frames_from_the_given_frame():
    """A latent model's frames 1.. are autoencoder decodes: a constant error against the given frame 0
    is not motion; a moving square is."""
    still = np.full((6, 16, 16, 3), 100, np.uint8)
    decoded = still.copy()
    decoded[1:] = 110  # every predicted frame off by the same codec error, nothing moves
    assert clip_motion(decoded) == 0.0
    moving = decoded.copy()
    for t in range(1, 6):
        moving[t, 4:8, 2 * t:2 * t + 4] = 250
    assert clip_motion(moving) > 1.0
    assert clip_motion(decoded[:2]) == pytest.approx(10.0)


def test_goals_table_reads_the_reports_numbers(two_checkpoints, tmp_path, capsys):
    from tesseract4d import cli
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, write_heldout_report

    a, b, heldout = two_checkpoints
    report = evaluate_heldout(HeldoutConfig(checkpoint=[a, b], data=heldout, num_steps=2), progress=False)
    write_heldout_report(report, tmp_path / "eval")
    capsys.readouterr()
    assert cli.main(["research", "goals", f"{tmp_path / 'eval'}=synthetic", "--references"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert header == ["measure (goal)", f"synthetic: {a.name}", "synthetic: v2", "synthetic: static world"]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip().strip("|").split("|")[1:]]
            for line in lines[2:] if line.startswith("| ")}
    s = report["summary"]
    psnr = rows["RGB PSNR, moving (≥ 22 dB)"]
    assert [float(c.split()[0]) for c in psnr] == [round(s[m]["rgb_psnr_db_moving"], 2) for m in (a.name, "v2", "static")]
    assert rows["4D Chamfer, moving (≤ 20 mm)"][2].split()[0] == f"{1000 * s['static']['chamfer_l1_m_moving']:.1f}"
    # The static world keeps still in the one "keep still" instruction and follows neither push.
    assert rows["instruction contrast (≥ 70%)"][2] == "1 / 3 (0.33) ✗"
    assert rows['"keep still" right'][2] == "1 / 1 (1.00)" and rows["active instructions right"][2] == "0 / 2 (0.00)"
    c = report["contrast"]["v2"]
    assert rows["instruction contrast (≥ 70%)"][1].startswith(f"{c['right']} / {c['instructions']} ")
    grid = s["static"]["token_grid_ratio"]
    assert rows["token grid ratio (0.8–1.25)"][2] == f"{grid:.3f} " + ("✓" if 0.8 <= grid <= 1.25 else "✗")
    assert any("noise seeds 0" in line and "2 steps" in line for line in lines)
    # Without --references only the checkpoints.
    assert cli.main(["research", "goals", str(tmp_path / "eval")]) == 0
    assert capsys.readouterr().out.splitlines()[0].count("eval: ") == 2
    # Piped into a reader that stops early (`| head`): a quiet stop, no traceback.
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "tesseract4d.cli", "research", "goals", str(tmp_path / "eval")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait() == 141 and "Traceback" not in err and "BrokenPipe" not in err, err


def test_goals_show_every_autoencoder_ceiling_of_a_report():
    """A run comparing decoders scores one ceiling per distinct autoencoder; --references shows each."""
    from tesseract4d.evaluation.goals import columns

    report = {"checkpoints": {"a": "/runs/v2_old", "b": "/runs/v2_new", "c": "/runs/student_new"},
              "summary": {k: {} for k in ("a", "b", "c", "a_autoencoder", "b_autoencoder", "static")}}
    labels = [c.label for c in columns(report, "tabletop", references=True)]
    assert labels == ["tabletop: v2_old", "tabletop: v2_new", "tabletop: student_new",
                      "tabletop: ceiling (v2_old's autoencoder)", "tabletop: ceiling (v2_new's autoencoder)",
                      "tabletop: static world"]
    del report["summary"]["b_autoencoder"]  # one autoencoder: the plain label, as before
    assert [c.label for c in columns(report, "t", references=True)][3] == "t: ceiling (autoencoder)"


def test_goals_refuses_what_is_not_a_heldout_report(tmp_path, capsys):
    from tesseract4d import cli

    (tmp_path / "empty").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "report.json").write_text(json.dumps({"rgb_psnr_db": 20.0}))
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "report.json").write_text(json.dumps({"format": "tesseract4d-heldout-eval", "format_version": 3}))
    (tmp_path / "torn").mkdir()
    (tmp_path / "torn" / "report.json").write_text('{"format": "tesseract4d-he')
    for folder, words in (("empty", "holds no report.json"), ("other", "not a held-out report"),
                          ("old", "format 3"), ("torn", "not a readable report")):
        assert cli.main(["research", "goals", str(tmp_path / folder)]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, err
