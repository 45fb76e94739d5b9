"""The shipped models predict the same clips, bit for bit, as when their digests were recorded.

A change that is meant to leave the shipped sampler alone (deleting an unused option, moving code)
must keep these digests. Each is the sha256 of a predicted episode's RGB, depth and normal arrays
(one fixed synthetic first frame, one instruction, seed 0, fp32, one thread). Floating-point
kernels differ between CPU kinds and thread counts, so the digests are recorded per CPU kind. Every
kind, recorded or not, also compares the clip's per-frame channel means (shipped_fingerprints.json,
recorded with the digests) within a tolerance far below what a change of the sampler moves.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tesseract4d.testing.synthetic_scene import group_episode
from tesseract4d.model.checkpoint import CHECKPOINTS_DIR
from tesseract4d.model.predict import load_pipeline, predict_episode

FINGERPRINTS = Path(__file__).with_name("shipped_fingerprints.json")
INSTRUCTION = "push the red cube to the right"
# (checkpoint, noise draws): v2-2step with its own sampler (two draws, the draw choice included); v2
# with its own 10 guided steps and guidance interval, one draw (to keep the test short).
CASES = [("v2-2step", None), ("v2", 1)]
# CPU kind (model name, ATen capability) -> checkpoint -> sha256 of the predicted arrays.
DIGESTS = {
    ("AMD EPYC", "AVX512"): {
        "v2-2step": "2f25679ea18374ba7213efd34f7951f3c0c69fac37bb686f04be50ca809afebe",
        "v2": "cbb4e4b5952396bc65d389b8e3b46950622b5db753e7ebe48a458e7f3b53f98b",
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


def clip_fingerprint(episode) -> np.ndarray:
    """(frames, 7): per frame the mean RGB (0-255), depth (m) and normal components of the clip."""
    cam = next(iter(episode.cameras.values()))
    t = len(cam.rgb)
    return np.concatenate([cam.rgb.reshape(t, -1, 3).mean(1), cam.depth_m.reshape(t, -1).mean(1, keepdims=True),
                           cam.normal_cam.reshape(t, -1, 3).mean(1)], 1)


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
    recorded = np.asarray(json.loads(FINGERPRINTS.read_text())[name])
    found = clip_fingerprint(episode)
    # (frames, 7): RGB means in 0-255, depth in metres, normal components; tolerances per column group.
    for columns, tolerance in ((slice(0, 3), 0.5), (slice(3, 4), 1e-3), (slice(4, 7), 2e-3)):
        worst = float(np.abs(found[:, columns] - recorded[:, columns]).max())
        assert worst <= tolerance, f"{name} predicts another clip than recorded (channel means off by {worst})"
    if kind in DIGESTS:  # bit for bit where the CPU kind's digest is recorded
        assert digest == DIGESTS[kind][name], f"{name} predicts a different clip than recorded on {kind}"
