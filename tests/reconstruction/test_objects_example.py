"""The README's object-layer example (``EXAMPLE``, to be pasted into the README as is) runs as written
in a fresh interpreter and prints the instructed object's predicted trajectory."""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import numpy as np

from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still
from tesseract4d.dataset_format import write_episode_dataset

EXAMPLE = '''\
from reconstruction.reconstruct import reconstruct_episode
from tesseract4d.dataset_format import read_episode, resolve_episode

first = read_episode(resolve_episode("data/truth"))  # the dataset episode the prediction started from
prediction = read_episode(resolve_episode("out/pred"))  # `tesseract4d predict --episode data/truth ... --out out/pred`
recon = reconstruct_episode(prediction, objects_from=first)  # objects named by the first frame's segmentation
track = recon.objects.instructed_track()  # the object the instruction is about
for t, (xyz, state) in enumerate(zip(track.positions_world(), track.states())):
    print(f"frame {t:2d}: {track.name} at {xyz.round(3)} m ({state})")
'''


def test_object_example_prints_the_instructed_objects_trajectory(tmp_path):
    assert len(EXAMPLE.splitlines()) <= 10
    T, half = 8, 0.02
    red = Box("cube", moving((0.0, 0.0, half), (0.08, 0.0, half), T), np.zeros(T), (half,) * 3, (220, 30, 30))
    green = Box("cube_b", still((-0.05, -0.09, half), T), np.zeros(T), (half,) * 3, (30, 200, 40))
    truth = box_episode([red, green], T, size=96, instruction="push the red cube forward 8 cm",
                        intent={"skill": "push", "target": "cube"})
    prediction = copy.deepcopy(truth)  # a "prediction" that moved the cube as the truth did, without segmentation
    prediction.source = "prediction"
    prediction.cameras["close"].segmentation = None
    prediction.object_poses = {}
    write_episode_dataset(tmp_path / "data" / "truth", truth)
    write_episode_dataset(tmp_path / "out" / "pred", prediction)
    (tmp_path / "example.py").write_text(EXAMPLE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == T and all(": cube at [" in line and line.endswith("(tracked)") for line in lines), lines
    start = np.array(lines[0].split("[")[1].split("]")[0].split(), float)
    end = np.array(lines[-1].split("[")[1].split("]")[0].split(), float)
    assert np.allclose(end - start, [0.08, 0.0, 0.0], atol=0.003)
