"""The one-command demo with the shipped checkpoint, as a user runs it: a counterfactual pair by
default (one held-out tabletop scene, two instructions, two futures side by side), one future
with `--set contrast=false`, the instruction defaults of a plain ManiSkill task and the refused options."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tesseract4d.dataset_format import HELDOUT_SEED_START


def cli(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "tesseract4d.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"tesseract4d {' '.join(map(str, args))} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def mp4_size(path: Path) -> tuple[int, int]:
    """(frame count, width) of an MP4, read with OpenCV."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        return int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    finally:
        cap.release()


@pytest.mark.sim
@pytest.mark.slow
def test_demo_predicts_a_counterfactual_pair(tmp_path):
    from tesseract4d import dataset_format as df

    out = tmp_path / "demo"
    proc = cli("demo", "--headless", "--out", out)
    config = json.loads((out / "demo_config.json").read_text())
    main, contrast = config["instruction"], config["contrast_instruction"]
    assert config["task"] == "Tesseract4dTabletop-v1" and config["seed"] == HELDOUT_SEED_START
    assert (config["skill"], config["contrast_skill"]) == ("push_left", "keep_still")
    assert "cube" in main and "left" in main and contrast and contrast != main
    assert f"instruction: {main}" in proc.stdout and f"contrast:    {contrast}" in proc.stdout
    assert str(out / "contrast" / "reconstruction") in proc.stdout and str(out / "side_by_side.mp4") in proc.stdout

    futures = {}
    for folder, text in ((out, main), (out / "contrast", contrast)):
        assert (folder / "instruction.txt").read_text().strip() == text
        assert len(list((folder / "reconstruction" / "frames").glob("*.ply"))) == config["num_frames"]
        assert (folder / "scene.html").stat().st_size > 10_000
        futures[text] = df.read_episode(df.resolve_episode(folder / "prediction"))
        assert futures[text].instruction == text
    assert list((out / "first_frame").rglob("*.h5"))

    # The same first frame, two different futures.
    a, b = (next(iter(futures[t].cameras.values())) for t in (main, contrast))
    assert np.array_equal(a.rgb[0], b.rgb[0]) and np.array_equal(a.depth_m[0], b.depth_m[0])
    assert np.abs(a.rgb[1:].astype(int) - b.rgb[1:].astype(int)).mean() > 0.5
    assert not np.allclose(a.depth_m[1:], b.depth_m[1:])

    # Both futures side by side, each half as wide as one future's preview.
    _, single_width = mp4_size(next((out / "prediction").rglob("*.mp4")))
    frames, width = mp4_size(out / "side_by_side.mp4")
    assert frames == config["num_frames"] and width == 2 * single_width


@pytest.mark.sim
@pytest.mark.slow
def test_demo_without_contrast_writes_one_future(tmp_path):
    out = tmp_path / "demo"
    proc = cli("demo", "--headless", "--task", "PushCube-v1", "--seed", HELDOUT_SEED_START + 1, "--set", "contrast=false",
               "--steps", 2, "--set", "draws=2", "--out", out)
    assert "instruction:" in proc.stdout and "contrast:" not in proc.stdout
    config = json.loads((out / "demo_config.json").read_text())
    assert config["contrast"] is False and config["contrast_instruction"] is None and config["instruction"]
    # Two noise draws, the kept one chosen by the rendered first frame's objects (its segmentation).
    from tesseract4d import dataset_format as df

    chosen = df.read_episode(df.resolve_episode(out / "prediction")).metadata["prediction"]["draws"]
    assert config["draws"] == 2 and chosen["count"] == 2 and chosen["kept"] in (0, 1)
    assert all(0.0 <= s <= 1.0 for s in chosen["objects_kept"])
    assert (out / "scene.html").is_file() and len(list((out / "reconstruction" / "frames").glob("*.ply"))) == 16
    assert list((out / "prediction").rglob("*.mp4")) and list((out / "first_frame").rglob("*.h5"))
    assert not (out / "contrast").exists() and not (out / "side_by_side.mp4").exists()


@pytest.mark.sim
def test_a_maniskill_task_keeps_its_instruction_and_contrasts_with_keeping_still():
    from datagen.simulate import first_frame_simulator
    from datagen.skill_language import TEMPLATES
    from tesseract4d.cli.demo import DemoConfig, resolve_instructions

    for task, has_contrast in (("PickCube-v1", True), ("LiftPegUpright-v1", False)):
        cfg = DemoConfig(task=task)
        sim = first_frame_simulator(task, height=32, width=32)
        try:
            first = sim.first_frame(cfg.seed)
            main, contrast, skills = resolve_instructions(cfg, sim, first)
        finally:
            sim.close()
        assert main == first.instruction and main  # the task's own held-out instruction, as before
        if has_contrast:
            assert contrast in TEMPLATES["keep_still"]["heldout"] and skills == {"skill": None, "contrast_skill": "keep_still"}
        else:  # the skill library does not know this scene: one future unless a text is given
            assert contrast is None


@pytest.mark.parametrize("argv, message", [
    (["--set", "contrast=false", "--contrast-instruction", "stay"], "contradict"),
    (["--instruction", "push it", "--skill", "push_left"], "--instruction and --skill"),
    (["--contrast-instruction", " "], "--contrast-instruction is empty"),
    (["--task", "PickCube-v1", "--skill", "stack"], "needs two objects"),
    (["--contrast-skill", "fly"], "unknown skill 'fly'"),
])
def test_contradicting_or_unknown_options_fail_in_one_line(tmp_path, capsys, argv, message):
    from tesseract4d.cli import main

    assert main(["demo", "--headless", "--out", str(tmp_path / "demo"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "demo").exists()
