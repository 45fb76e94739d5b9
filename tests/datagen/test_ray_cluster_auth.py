"""`datagen --set ray_address=HEAD:PORT` warns about a Ray cluster that asks for no authentication token (anyone
reaching it can run code on its machines), and says nothing of the kind for a token cluster."""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

REPO = str(Path(__file__).resolve().parents[2])
RAY = str(Path(sys.executable).with_name("ray"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _head(env: dict, temp: Path, port: int) -> subprocess.Popen:
    head = subprocess.Popen([RAY, "start", "--head", "--block", "--node-ip-address", "127.0.0.1", "--port", str(port),
                             "--temp-dir", str(temp), "--num-cpus", "1", "--include-dashboard", "false",
                             "--disable-usage-stats"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    deadline = time.time() + 120
    for line in head.stdout:
        if "Ray runtime started" in line or time.time() > deadline:
            break
    assert head.poll() is None, "ray start --head exited"
    return head


@pytest.mark.slow
@pytest.mark.parametrize("token", [False, True], ids=["no-token", "token"])
def test_a_cluster_without_token_authentication_is_warned_about(token):
    temp = Path(tempfile.mkdtemp(prefix="t4a", dir="/tmp"))  # unix socket paths must stay short
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    # Explicit either way: with RAY_AUTH_MODE unset, Ray 2.60 turns token mode on when ~/.ray/auth_token exists.
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(16)) if token else env.update(RAY_AUTH_MODE="disabled")
    head = _head(env, temp, port)
    try:
        # In a process of its own, as datagen runs it: Ray caches its authentication settings per process.
        check = subprocess.run([sys.executable, "-c", "import sys; from datagen.generate import check_ray_cluster; "
                                "check_ray_cluster(sys.argv[1])", f"127.0.0.1:{port}"], env=dict(env, PYTHONPATH=REPO),
                               capture_output=True, text=True, timeout=120)
        assert check.returncode == 0, check.stderr[-2000:]
        if token:
            assert "warning" not in check.stderr, check.stderr
        else:
            assert "does not ask for an authentication token" in check.stderr, check.stderr
            assert "RAY_AUTH_MODE=token" in check.stderr
    finally:
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        shutil.rmtree(temp, ignore_errors=True)
