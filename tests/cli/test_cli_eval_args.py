"""`evaluate`, `rollout` and `reconstruct` options: a bad number ends at parse time (exit 2, the flag,
the rule and the value on stderr) before anything is read or written; help that a user can act on;
a warning when a prediction is scored against another scene's ground truth."""

from __future__ import annotations

import pytest
from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

from tesseract4d import cli

ENV = "Synthetic-v0"


def refused(capsys, argv: list[str]) -> str:
    """stderr of a command that must end at parse time with exit 2."""
    with pytest.raises(SystemExit) as ended:
        cli.main(argv)
    err = capsys.readouterr().err
    assert ended.value.code == 2, err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("flag, value, said", [
    ("--max-per-task", "0", "argument --max-per-task: must be a whole number >= 1, got '0'"),
    ("--max-per-task", "-1", "argument --max-per-task: must be a whole number >= 1, got '-1'"),
    ("--steps", "0", "argument --steps: must be a whole number >= 1, got '0'"),
    ("--steps", "-1", "argument --steps: must be a whole number >= 1, got '-1'"),
    ("--text-guidance", "-1", "argument --text-guidance: must be a finite number > 0 (1: no guidance), got '-1'"),
    ("--text-guidance", "0", "argument --text-guidance: must be a finite number > 0 (1: no guidance), got '0'"),
    ("--text-guidance", "nan", "argument --text-guidance: must be a finite number > 0"),
    ("--batch-size", "0", "argument --batch-size: must be a whole number >= 1, got '0'"),
    ("--sample-seed", "-1", "argument --sample-seed: must be a whole number in 0..4294967295, got '-1'"),
    ("--max-depth", "0", "argument --max-depth: must be a finite number > 0, got '0'"),
    ("--max-depth", "-1", "argument --max-depth: must be a finite number > 0, got '-1'"),
])
def test_evaluate_heldout_refuses_bad_numbers_before_any_work(tmp_path, capsys, flag, value, said):
    out = tmp_path / "out"
    err = refused(capsys, ["evaluate", "--heldout", str(tmp_path / "data"), "--out", str(out), flag, value])
    assert said in err
    assert not out.exists()


def test_evaluate_max_depth_is_refused_for_a_prediction_too(tmp_path, capsys):
    report = tmp_path / "r.json"
    err = refused(capsys, ["evaluate", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"), "--json", str(report),
                           "--max-depth", "-1"])
    assert "argument --max-depth: must be a finite number > 0, got '-1'" in err
    assert not report.exists()


@pytest.mark.parametrize("flag, value, said", [
    ("--resolution", "0", "argument --resolution: must be a whole number in 1..2048, got '0'"),
    ("--resolution", "-64", "argument --resolution: must be a whole number in 1..2048, got '-64'"),
    ("--episodes", "0", "argument --episodes: must be a whole number >= 1, got '0'"),
    ("--episodes", "-1", "argument --episodes: must be a whole number >= 1, got '-1'"),
    ("--max-steps", "0", "argument --max-steps: must be a whole number >= 1, got '0'"),
    ("--max-steps", "-5", "argument --max-steps: must be a whole number >= 1, got '-5'"),
    ("--sample-steps", "0", "argument --sample-steps: must be a whole number >= 1, got '0'"),
    ("--draws", "0", "argument --draws: must be a whole number >= 1 (1: a single draw), got '0'"),
    ("--replan-every", "0", "argument --replan-every: must be a whole number in 1..15 (a clip has 16 frames), got '0'"),
    ("--replan-every", "16", "argument --replan-every: must be a whole number in 1..15"),
    ("--seed-start", "-1", "argument --seed-start: must be a whole number in 0..4294967295, got '-1'"),
    ("--videos", "-1", "argument --videos: must be a whole number >= 0, got '-1'"),
    ("--viewer-episodes", "-1", "argument --viewer-episodes: must be a whole number >= 0, got '-1'"),
])
def test_rollout_refuses_bad_numbers_before_writing_anything(tmp_path, capsys, flag, value, said):
    out = tmp_path / "rollouts"
    err = refused(capsys, ["rollout", "--tasks", "PushCube-v1", "--arms", "motion_planner", "--out", str(out), flag, value])
    assert said in err
    assert not out.exists()  # no rollout_config.json left behind


@pytest.mark.parametrize("flag, value, said", [
    ("--flow-threshold", "-1", "argument --flow-threshold: must be a finite number > 0 pixels, got '-1'"),
    ("--flow-threshold", "0", "argument --flow-threshold: must be a finite number > 0 pixels, got '0'"),
    ("--iterations", "0", "argument --iterations: must be a whole number >= 1, got '0'"),
    ("--voxel-size", "0", "argument --voxel-size: must be a finite number > 0, got '0'"),
    ("--static-weight", "-1", "argument --static-weight: must be a finite number >= 0, got '-1'"),
    ("--dynamic-weight", "nan", "argument --dynamic-weight: must be a finite number >= 0"),
    ("--normal-weight", "inf", "argument --normal-weight: must be a finite number >= 0"),
    ("--reg-weight", "0", "argument --reg-weight: must be a finite number > 0 (it fixes the depth scale), got '0'"),
])
def test_reconstruct_refuses_bad_numbers_with_the_flag_name(tmp_path, capsys, flag, value, said):
    out = tmp_path / "recon"
    err = refused(capsys, ["reconstruct", str(tmp_path / "episode.h5"), "--out", str(out), flag, value])
    assert said in err and "ReconConfig" not in err
    assert not out.exists()


def test_help_says_what_a_user_can_act_on(capsys):
    from tesseract4d.model.predict import DEFAULT_SCENE_BATCH

    with pytest.raises(SystemExit):
        cli.main(["evaluate", "--set", "list"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"scenes predicted together in one network call (default {DEFAULT_SCENE_BATCH};" in text
    for name in ("evaluate", "rollout"):
        with pytest.raises(SystemExit):
            cli.main([name, "--help"])
        text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
        if name == "evaluate":
            assert "DEFAULT_SCENE_BATCH" not in text and "predict_scenes" not in text
            # The example's line continuation survives: the second line starts with its own option.
            assert "checkpoints/v2 \\ --checkpoint tesseract4d/checkpoints/v2-2step" in text
        else:
            assert "--quiet no progress bar" in text


# --------------------------------------------------------------------------- scored scene


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("scenes") / "data", episodes=2)


def scored(capsys, pred, gt) -> str:
    assert cli.main(["evaluate", str(pred), "--gt", str(gt), "--no-per-frame"]) == 0
    return capsys.readouterr().err


def test_a_prediction_scored_against_another_scene_is_warned_about(data, capsys):
    err = scored(capsys, data / ENV / "0", data / ENV / "1")
    assert (f"warning: the prediction is of {ENV} seed 0 but the ground truth is of {ENV} seed 1: the metrics "
            f"compare two different scenes; pass the ground truth of {ENV} seed 0 as --gt") in err
    assert "warning" not in scored(capsys, data / ENV / "1", data / ENV / "1")


def test_a_reconstruction_scored_against_another_scene_is_warned_about(data, tmp_path, capsys):
    recon = tmp_path / "recon"
    assert cli.main(["reconstruct", str(data / ENV / "0"), "--out", str(recon), "--no-refine", "--no-mesh", "--no-ply",
                     "--quiet"]) == 0
    assert f"ground truth is of {ENV} seed 1" in scored(capsys, recon, data / ENV / "1")
    assert "warning" not in scored(capsys, recon, data / ENV / "0")
