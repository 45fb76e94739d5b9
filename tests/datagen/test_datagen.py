"""Data generation: instructions (pure), a real datagen run through the CLI, re-simulation from
the stored metadata, resume after a killed run, dataset info/check, and bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import SIM_CAMERAS, SIM_FRAMES, SIM_SIZE

from datagen.instructions import TEMPLATES, direction_words, make_instruction, scene_attributes
from datagen.simulate import frame_indices
from datagen.tasks import TASKS
from tesseract4d.cli import main
from tesseract4d.dataset_format import list_episode_files, read_episode

REPO = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- pure


def test_every_task_has_train_and_disjoint_heldout_paraphrases():
    assert set(TEMPLATES) == {t for t, spec in TASKS.items() if not spec.skills_only}  # skill scenes: skill_language
    for env_id, t in TEMPLATES.items():
        assert len(t["train"]) >= 3 and len(t["heldout"]) >= 2, env_id
        assert not set(t["train"]) & set(t["heldout"]), env_id


def test_direction_words_follow_the_robot_frame():
    assert direction_words(np.array([0.1, 0.0])) == "forward"
    assert direction_words(np.array([-0.1, 0.01])) == "back"
    assert direction_words(np.array([0.0, 0.1])) == "to the left"
    assert direction_words(np.array([0.1, -0.08])) == "forward and to the right"
    assert direction_words(np.array([0.005, 0.0])) == "in place"


def test_instructions_vary_with_the_scene():
    rng = np.random.default_rng(0)
    texts = set()
    for color in ("red", "blue"):
        for goal in ([0.1, 0.0, 0.3], [0.0, -0.1, 0.05]):
            attrs = scene_attributes("PickCube-v1", {"cube": np.zeros(3), "goal": np.array(goal)}, {"cube": color})
            text = make_instruction("PickCube-v1", attrs, rng, split="heldout")
            assert color in text
            texts.add(text)
    assert len(texts) == 4
    assert any("forward" in t for t in texts) and any("right" in t for t in texts)


def test_frame_indices_are_evenly_spaced_and_keep_both_ends():
    idx = frame_indices(75, 16)
    assert len(idx) == 16 and idx[0] == 0 and idx[-1] == 74 and np.all(np.diff(idx) > 0)
    assert len(frame_indices(10, 0)) == 10 and len(frame_indices(10, 50)) == 10


# --------------------------------------------------------------------------- a real run


@pytest.fixture(scope="module")
def small_dataset(sim_dataset):
    """The run's simulator dataset (conftest.py): PickCube-v1, two cameras, randomised, jittered."""
    return sim_dataset


@pytest.mark.sim
def test_datagen_writes_a_complete_episode(small_dataset):
    files = list_episode_files(small_dataset)
    assert len(files) == 1
    ep = read_episode(files[0])
    assert ep.success is True and ep.num_frames == SIM_FRAMES and ep.control_mode == "pd_joint_pos"
    assert ep.frame_steps[0] == 0 and ep.frame_steps[-1] == len(ep.actions) > 10
    assert set(ep.cameras) == set(SIM_CAMERAS)
    for cam in ep.cameras.values():
        assert cam.rgb.shape == (SIM_FRAMES, SIM_SIZE, SIM_SIZE, 3) and cam.rgb.std() > 5
        assert (cam.depth_m > 0).mean() > 0.9 and cam.depth_m.max() < 20
        norms = np.linalg.norm(cam.normal_cam, axis=-1)
        assert np.abs(norms[cam.depth_m > 0] - 1).max() < 5e-3
        assert "cube" in cam.seg_id_to_name.values()
    # The arm moved and the cube was lifted to the goal.
    assert np.abs(ep.qpos[-1] - ep.qpos[0]).max() > 0.1
    cube, goal = ep.object_poses["cube"], ep.object_poses["goal"]
    assert cube[-1, 2] > cube[0, 2] + 0.01 and np.linalg.norm(cube[-1, :3] - goal[-1, :3]) < 0.025
    color = ep.metadata["appearance"]["colors"]["cube"]
    assert color in ep.instruction
    assert ep.metadata["instruction_attributes"]["color"] == color
    assert ep.metadata["package_versions"]["mani-skill"] == "3.0.1"
    assert ep.metadata["camera_views"]["close"]["eye"] != list(TASKS["PickCube-v1"].close_eye)  # jittered
    report = json.loads((small_dataset / "datagen_report.json").read_text())
    assert report["tasks"]["PickCube-v1"]["successes"] == 1
    config = json.loads((small_dataset / "datagen_config.json").read_text())
    assert config["sim"]["height"] == SIM_SIZE and config["tasks"] == ["PickCube-v1"]


@pytest.mark.sim
def test_preview_is_browser_playable_h264(small_dataset):
    import imageio.v2 as imageio

    mp4 = next((small_dataset / "previews" / "PickCube-v1").glob("seed_*.mp4"))
    reader = imageio.get_reader(mp4, format="FFMPEG")
    meta = reader.get_meta_data()
    frames = [f for f in reader]
    reader.close()
    assert meta["codec"] == "h264" and "yuv420p" in meta.get("pix_fmt", "")
    assert len(frames) == SIM_FRAMES and frames[0].shape[1] == 3 * frames[0].shape[0]  # RGB | depth | normal


@pytest.mark.sim
def test_stored_metadata_re_simulates_the_episode(small_dataset):
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    ep = read_episode(list_episode_files(small_dataset)[0])
    env = gym.make(ep.env_id, control_mode=ep.control_mode, **ep.env_kwargs)
    try:
        env.reset(seed=ep.seed)
        for a in ep.actions:
            _, _, _, _, info = env.step(a)
        cube = env.unwrapped.cube.pose.raw_pose[0].numpy()
        assert bool(info["success"])
    finally:
        env.close()
    np.testing.assert_allclose(cube[:3], ep.object_poses["cube"][-1, :3], atol=1e-4)


@pytest.mark.sim
def test_dataset_info_and_check(small_dataset, capsys, tmp_path):
    assert main(["dataset", "info", str(small_dataset)]) == 0
    out = capsys.readouterr().out
    assert "episodes  1" in out and "PickCube-v1" in out and f"frames {SIM_FRAMES}" in out
    assert main(["dataset", "check", str(small_dataset)]) == 0
    assert "1 ok, 0 bad" in capsys.readouterr().out
    # A truncated shard in a copy: check names it and fails; the good data is untouched.
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(small_dataset, copy)
    shard = list_episode_files(copy)[0]
    shard.write_bytes(shard.read_bytes()[:5000])
    assert main(["dataset", "check", str(copy)]) == 1
    out = capsys.readouterr().out
    assert f"BAD  {shard}" in out and "corrupt or truncated" in out
    assert read_episode(list_episode_files(small_dataset)[0]).num_frames == SIM_FRAMES


# --------------------------------------------------------------------------- resume


@pytest.mark.sim
def test_resume_after_a_killed_run(tmp_path):
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "tesseract4d.cli", "datagen", "--tasks", "PushCube-v1", "--episodes", "3",
           "--out", str(out), "--resolution", "32", "--frames", "4", "--set", "previews=false", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not list_episode_files(out) and proc.poll() is None:
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    done = {p: p.stat().st_mtime_ns for p in list_episode_files(out)}
    assert 1 <= len(done) < 3, "the run should be killed after its first episode"
    # What a kill in the middle of a write leaves behind.
    partial = out / "episodes" / "PushCube-v1" / ".seed_000002.0123abcd.partial.h5"
    partial.write_bytes(b"\x89HDF half-written")
    n_logged_before = len((out / "datagen_attempts.jsonl").read_text().splitlines())

    assert main(cmd[3:]) == 0
    files = list_episode_files(out)
    assert len(files) == 3 and not partial.exists()
    for p, mtime in done.items():
        assert p.stat().st_mtime_ns == mtime  # finished episodes were not redone
    done_seeds = {int(p.stem.split("_")[1]) for p in done}
    rerun = [json.loads(line) for line in (out / "datagen_attempts.jsonl").read_text().splitlines()[n_logged_before:]]
    assert rerun and not {r["seed"] for r in rerun} & done_seeds
    report = json.loads((out / "datagen_report.json").read_text())
    assert report["this_run"]["episodes_written"] == 3 - len(done)


# --------------------------------------------------------------------------- bad input


def test_unknown_task_lists_the_valid_ones(tmp_path, capsys):
    assert main(["datagen", "--tasks", "PickCub-v1", "--episodes", "1", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "unknown or unsupported task 'PickCub-v1'" in err and "PickCube-v1" in err and "PegInsertionSide-v1" in err
    assert not (tmp_path / "x").exists()


def test_task_needing_downloaded_assets_says_so(tmp_path, capsys):
    assert main(["datagen", "--tasks", "PickSingleYCB-v1", "--episodes", "1", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "needs downloaded assets" in err and "ycb" in err


def test_bad_camera_preset(tmp_path, capsys):
    assert main(["datagen", "--tasks", "PickCube-v1", "--episodes", "1", "--out", str(tmp_path / "x"),
                 "--cameras", "wrist"]) == 2
    assert "unknown camera preset 'wrist'" in capsys.readouterr().err


def test_output_folder_of_another_format_version(tmp_path, capsys):
    (tmp_path / "info.json").write_text(json.dumps({"format_version": 99}))
    (tmp_path / "keep.txt").write_text("existing data")
    assert main(["datagen", "--tasks", "PickCube-v1", "--episodes", "1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "format version 99" in err and "new folder" in err
    assert (tmp_path / "keep.txt").read_text() == "existing data"
    assert json.loads((tmp_path / "info.json").read_text()) == {"format_version": 99}


@pytest.mark.sim
def test_broken_vulkan_driver_says_how_to_install_one(tmp_path):
    icd = tmp_path / "broken_icd.json"
    icd.write_text(json.dumps({"file_format_version": "1.0.0",
                               "ICD": {"library_path": str(tmp_path / "libvulkan_missing.so"), "api_version": "1.3.0"}}))
    env = dict(os.environ, VK_ICD_FILENAMES=str(icd), VK_DRIVER_FILES=str(icd))
    proc = subprocess.run(
        [sys.executable, "-m", "tesseract4d.cli", "datagen", "--tasks", "PickCube-v1", "--episodes", "1",
         "--out", str(tmp_path / "ds"), "--quiet"], cwd=REPO, env=env, capture_output=True, text=True, timeout=180,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "scripts/setup.sh" in proc.stderr and "Vulkan" in proc.stderr
    assert not list_episode_files(tmp_path / "ds")


def test_datagen_modules_import_without_the_simulator():
    code = ("import sys, tesseract4d.cli.datagen, tesseract4d.cli.dataset, datagen.simulate, datagen.generate, datagen.capture, "
            "tesseract4d.previews; print(','.join(m for m in ('torch', 'mani_skill', 'sapien', 'ray', 'gymnasium') "
            "if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ""


def test_a_resumed_datagen_writes_the_previews_an_interrupted_run_did_not_finish(tmp_path):
    """An interrupt between an episode's file and its MP4 preview leaves the episode without one; the
    next run into the folder writes it (and leaves the others as they are)."""
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from datagen.generate import _write_missing_previews
    from tesseract4d.dataset_format import preview_path, read_episode_attrs
    from tesseract4d.previews import write_preview

    root = write_synthetic_dataset(tmp_path / "ds", episodes=2)
    files = list_episode_files(root)
    kept = write_preview(root, read_episode(files[0]))
    kept_mtime = kept.stat().st_mtime_ns
    attrs = read_episode_attrs(files[1])
    lost = preview_path(root, attrs["env_id"], attrs["seed"], attrs["variant"])
    lost.unlink(missing_ok=True)
    assert _write_missing_previews(root) == [lost]
    assert lost.stat().st_size > 0 and kept.stat().st_mtime_ns == kept_mtime
    assert _write_missing_previews(root) == []
