"""The README's object-layer example runs as written in a fresh interpreter and prints the instructed
object's predicted trajectory."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still
from tesseract4d.dataset_format import write_episode_dataset

README = Path(__file__).resolve().parents[2] / "README.md"


def readme_object_example() -> str:
    """The README's ```python block that follows its "scene as objects" paragraph."""
    text = README.read_text()
    begin = text.index("```python\n", text.index("also holds the scene as objects")) + len("```python\n")
    return text[begin:text.index("```", begin)]


def test_object_example_prints_the_instructed_objects_trajectory(tmp_path):
    example = readme_object_example()
    assert len(example.splitlines()) <= 10
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
    (tmp_path / "example.py").write_text(example)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == T and all(": cube at [" in line and line.endswith("(tracked)") for line in lines), lines
    start = np.array(lines[0].split("[")[1].split("]")[0].split(), float)
    end = np.array(lines[-1].split("[")[1].split("]")[0].split(), float)
    assert np.allclose(end - start, [0.08, 0.0, 0.0], atol=0.003)
