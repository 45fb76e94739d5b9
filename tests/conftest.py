"""Shared test set-up: the same runtime environment as the CLI, and an artifacts folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tesseract4d import runtime

runtime.configure()

ARTIFACTS_DIR = Path(os.environ.get("TESSERACT4D_TEST_ARTIFACTS", Path(__file__).resolve().parent.parent / "test-artifacts"))


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    """A folder for files a person may want to look at after the run (screenshots, previews)."""
    ARTIFACTS_DIR.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS_DIR


@pytest.fixture(scope="session")
def micro_preset():
    """The micro preset (model_fixtures.MICRO) registered in PRESETS for the whole run, so that
    tests train, export and load it by name."""
    from tesseract4d.testing.model_fixtures import MICRO

    from tesseract4d.model.presets import PRESETS

    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(PRESETS, MICRO.name, MICRO)
        yield MICRO


@pytest.fixture(scope="session")
def micro_checkpoint(micro_preset, tmp_path_factory) -> Path:
    """A micro checkpoint trained 10 steps on two synthetic episodes, for the tests that only read it."""
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.trainer import TrainConfig, Trainer

    root = tmp_path_factory.mktemp("micro_checkpoint")
    data = write_synthetic_dataset(root / "data", episodes=2)
    return Trainer(TrainConfig(data=data, out=root / "run", preset=micro_preset.name, max_steps=10, val_every=0,
                               ckpt_every=0, quiet=True)).train()


# The one simulator dataset of the run: a PickCube-v1 episode from `tesseract4d datagen` with
# every option of the real thing (two cameras, randomised colours and lighting, camera jitter,
# MP4 preview). Generated once, read by the datagen, reconstruction and dataset tests.
SIM_TASK, SIM_SIZE, SIM_FRAMES, SIM_CAMERAS = "PickCube-v1", 64, 16, ("close", "base_camera")


@pytest.fixture(scope="session")
def sim_dataset(tmp_path_factory) -> Path:
    from tesseract4d.cli import main

    out = tmp_path_factory.mktemp("sim_dataset") / "ds"
    argv = ["datagen", "--tasks", SIM_TASK, "--episodes", "1", "--out", str(out), "--resolution", str(SIM_SIZE),
            "--frames", str(SIM_FRAMES), "--cameras", ",".join(SIM_CAMERAS), "--randomize-colors",
            "--randomize-lighting", "--camera-jitter", "0.02", "--quiet"]
    assert main(argv) == 0
    return out
