"""`datagen --workers N` on one machine: nothing of it listens on the network, and its worker
processes end with the driver, even when the driver is killed outright (SIGKILL)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[2]
DATAGEN = [sys.executable, "-m", "tesseract4d.cli", "datagen", "--tasks", "PushCube-v1", "--resolution", "32",
           "--frames", "4", "--set", "previews=false", "--quiet", "--workers", "2"]


def _tree(pid: int) -> list[psutil.Process]:
    try:
        root = psutil.Process(pid)
        return [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _finished(dataset: Path) -> list[str]:
    """The episode files a datagen run has finished in ``dataset`` (not the hidden ``.*.partial.h5`` being written)."""
    return sorted(p.name for p in dataset.glob("episodes/*/*.h5") if not p.name.startswith("."))


def _listening(procs: list[psutil.Process]) -> list[tuple]:
    found = []
    for p in procs:
        try:
            found += [(p.pid, p.name(), c.laddr) for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return found


@pytest.mark.sim
@pytest.mark.slow
def test_local_workers_listen_nowhere_and_end_with_a_killed_driver(tmp_path):
    env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    proc = subprocess.Popen([*DATAGEN, "--episodes", "6", "--out", str(tmp_path / "ds")], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        seen, listening = set(), []
        while not _finished(tmp_path / "ds"):  # watch until the workers have written one
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
            tree = _tree(proc.pid)
            seen |= {p.pid for p in tree[1:]}
            listening += _listening(tree)
            time.sleep(0.5)
        workers = [p for p in _tree(proc.pid)[1:]]
        assert len(workers) >= 2, workers
        assert listening == [], listening
        proc.kill()  # SIGKILL: the driver runs no clean-up at all
        proc.wait(timeout=30)
        gone, alive = psutil.wait_procs(workers, timeout=15)
        assert alive == [], [(p.pid, p.cmdline()) for p in alive]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in _tree(proc.pid):
            p.kill()
    # The next run resumes in the same folder: the killed run's partial files are cleared, no episode is lost.
    before = _finished(tmp_path / "ds")
    done = subprocess.run([*DATAGEN, "--episodes", "3", "--out", str(tmp_path / "ds")], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    after = _finished(tmp_path / "ds")
    assert set(before) <= set(after) and len(after) >= 3
    assert not list((tmp_path / "ds").glob("episodes/*/.*partial*"))
