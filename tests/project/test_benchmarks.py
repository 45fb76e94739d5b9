"""Benchmarks are run on demand, not by the suite; this keeps each one at least starting: its --help
parses (the module's top-level imports resolve), and the shared machine line names what a timing
needs beside it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if p.name != "measure.py")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_benchmark_help_runs(script: Path) -> None:
    done = subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage:" in done.stdout


def test_machine_line_names_cpu_threads_and_load(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import torch  # noqa: F401  (loaded, so the line names its threads)
    from measure import machine_line

    line = machine_line("precision bf16")
    assert line.startswith("CPU: ")
    for part in ("logical CPUs", "threads", "OMP_WAIT_POLICY=", "load average ", "precision bf16"):
        assert part in line, line
