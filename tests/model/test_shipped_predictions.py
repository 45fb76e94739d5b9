"""The shipped models predict the same clips, bit for bit, as when their digests were recorded.

A change that is meant to leave the shipped sampler alone (deleting an unused option, moving code)
must keep these digests. Each is the sha256 of a predicted episode's RGB, depth and normal arrays
(one fixed synthetic first frame, one instruction, seed 0, fp32, one thread). Floating-point
kernels differ between CPU kinds and thread counts, so the digests are recorded per CPU kind; on a
kind without a record the test says how to record one instead of comparing.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from tesseract4d.testing.synthetic_scene import group_episode
from tesseract4d.model.checkpoint import CHECKPOINTS_DIR
from tesseract4d.model.predict import load_pipeline, predict_episode

INSTRUCTION = "push the red cube to the right"
# (checkpoint, noise draws): v2-2step with its own sampler (two draws, the draw choice included); v2
# with its own 10 guided steps and guidance interval, one draw (to keep the test short).
CASES = [("v2-2step", None), ("v2", 1)]
# CPU kind (model name, ATen capability) -> checkpoint -> sha256 of the predicted arrays.
DIGESTS = {
    ("AMD EPYC", "AVX512"): {
        "v2-2step": "509dac6189855b725ca0673e901949d0b8ea0e0c455d57536463caa7d687bac1",
        "v2": "617a4794c0db1060626c53147e323ef2b660709dc11992208783fc4694aeb1b3",
    },
}


def cpu_kind() -> tuple[str, str]:
    model = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), model)
    except OSError:
        pass
    return model, torch.backends.cpu.get_cpu_capability()


def clip_digest(episode) -> str:
    cam = next(iter(episode.cameras.values()))
    h = hashlib.sha256()
    for a in (cam.rgb, cam.depth_m, cam.normal_cam):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("name,draws", CASES)
def test_shipped_checkpoint_predicts_its_recorded_clip(name, draws, one_thread):
    first = group_episode(0, scale=4)  # two coloured squares and a robot block, 128x128
    pipe = load_pipeline(CHECKPOINTS_DIR / name, precision="fp32")
    episode = predict_episode(pipe, first, INSTRUCTION, seed=0, draws=draws)
    digest = clip_digest(episode)
    kind = cpu_kind()
    if kind not in DIGESTS:
        pytest.skip(f"no digests recorded for CPU {kind}; record them from the unchanged code ({name}: {digest})")
    assert digest == DIGESTS[kind][name], f"{name} predicts a different clip than recorded on {kind}"
