"""The README's Python API example runs as written and writes what it says."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


def python_block(section: str) -> str:
    """The first ```python block after the heading ``section``."""
    text = README.read_text()
    start = text.index(section)
    begin = text.index("```python\n", start) + len("```python\n")
    return text[begin:text.index("```", begin)]


@pytest.mark.sim
@pytest.mark.slow
def test_python_api_example_runs_as_written(tmp_path):
    script = tmp_path / "example.py"
    script.write_text(python_block("## Python API"))
    # A fresh interpreter in an empty folder, as a user runs it; it configures its own runtime.
    env = {k: v for k, v in os.environ.items() if not k.startswith(("VK_", "MS_", "HF_", "TRANSFORMERS_"))}
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert list((tmp_path / "prediction" / "episodes" / "PushCube-v1").glob("seed_*.h5"))
    assert list((tmp_path / "prediction" / "previews" / "PushCube-v1").glob("seed_*.mp4"))
    assert (tmp_path / "reconstruction" / "recon4d.npz").is_file()
    assert (tmp_path / "scene.html").stat().st_size > 10_000
