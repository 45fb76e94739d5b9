"""Interrupts and permissions around outputs (tesseract4d/outputs.py, tesseract4d/cli/__init__.py): a
signal waits for a folder swap or a shard to finish, SIGTERM stops a command as Ctrl-C does (its
staging removed), and an output this user cannot write is refused before any work."""

from __future__ import annotations

import os
import signal

import pytest

from tesseract4d import cli
from tesseract4d.errors import UserError
from tesseract4d.outputs import OutputDir, check_writable, signals_held


@pytest.fixture
def ctrl_c():
    """SIGINT raising KeyboardInterrupt, as in a terminal (a suite started in the background inherits
    SIGINT ignored); the handler before is restored after."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_signal_inside_a_held_block_is_delivered_after_it(ctrl_c):
    happened = []
    with pytest.raises(KeyboardInterrupt):
        with signals_held():
            os.kill(os.getpid(), signal.SIGINT)
            happened.append("the block ran to its end")
    assert happened == ["the block ran to its end"]


def test_sigterm_stops_a_command_as_an_interrupt_and_its_stage_is_removed(tmp_path):
    """Under the command line's handler SIGTERM raises Terminated (a KeyboardInterrupt), so an output
    being staged is removed and nothing is left beside it; the previous handler comes back after."""
    before = signal.getsignal(signal.SIGTERM)
    previous = cli._stop_cleanly_on_sigterm()
    try:
        with pytest.raises(cli.Terminated):
            with OutputDir(tmp_path / "out", "predict") as stage:
                (stage / "half.txt").write_text("half")
                os.kill(os.getpid(), signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert signal.getsignal(signal.SIGTERM) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_an_earlier_result_survives_a_signal_during_its_replacement(tmp_path, monkeypatch, ctrl_c):
    """A signal that arrives while a rerun's result is being swapped in (here: right after the first
    rename of the swap) lands after the swap: the folder holds the new result whole, and no hidden
    copy of the old one is left beside it."""
    with OutputDir(tmp_path / "out", "predict") as stage:
        (stage / "result.txt").write_text("old")
    rename = os.replace

    def rename_then_signal(src, dst):
        rename(src, dst)
        os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        with OutputDir(tmp_path / "out", "predict") as stage:
            (stage / "result.txt").write_text("new")
            monkeypatch.setattr(os, "replace", rename_then_signal)  # the swap begins on leaving the block
    monkeypatch.undo()
    assert (tmp_path / "out" / "result.txt").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_an_output_this_user_cannot_write_is_refused_before_any_work(tmp_path, monkeypatch):
    """os.access answers as the kernel would for a user without write permission on ``locked``
    (this suite may run as root, for whom every folder is writable)."""
    locked = tmp_path / "locked"
    (locked / "earlier").mkdir(parents=True)
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p).startswith(str(locked)) else real_access(p, mode))
    for out in (locked / "new", locked / "a" / "b", locked / "earlier"):
        with pytest.raises(UserError, match=f"{locked}.* is not writable by this user"):
            check_writable(out)
    check_writable(tmp_path / "free")


def _killed_while_staging(out) -> None:
    """A real run of OutputDir killed with SIGKILL (which no handler can catch) in the middle of its
    staging folder."""
    import subprocess
    import sys

    code = ("import os, signal, sys\n"
            "from tesseract4d.outputs import OutputDir\n"
            "with OutputDir(sys.argv[1], 'predict') as stage:\n"
            "    (stage / 'half.txt').write_text('half')\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    done = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True)
    assert done.returncode == -signal.SIGKILL


def test_the_next_run_names_what_a_killed_run_left_and_keeps_it(tmp_path, capsys):
    _killed_while_staging(tmp_path / "out")
    (left,) = [p for p in tmp_path.iterdir()]
    assert left.name.startswith(".out.tmp-") and (left / "half.txt").read_text() == "half"
    (tmp_path / ".out.tmp-mine").mkdir()          # not a stage's name: the user's own
    (tmp_path / ".outer.tmp-abcdefgh").mkdir()    # the stage of another output
    with OutputDir(tmp_path / "out", "predict") as stage:
        (stage / "result.txt").write_text("new")
    err = capsys.readouterr().err
    assert f"note: {left} is a staging folder of a run writing {tmp_path / 'out'} that was killed" in err
    assert err.count("note:") == 1
    assert (left / "half.txt").read_text() == "half"  # never removed: a run may still be writing it
    assert (tmp_path / "out" / "result.txt").read_text() == "new"


def test_a_result_moved_aside_by_a_killed_swap_is_named_as_the_only_copy(tmp_path, capsys):
    """A kill between the two renames of a swap leaves the earlier result in ``.NAME.old-*/x`` and
    no NAME; the next run says where it is."""
    aside = tmp_path / ".out.old-k1ll3d_x"
    (aside / "x").mkdir(parents=True)
    (aside / "x" / "result.txt").write_text("old")
    with OutputDir(tmp_path / "out", "predict") as stage:
        (stage / "result.txt").write_text("new")
    err = capsys.readouterr().err
    assert f"note: {aside / 'x'} is an earlier result of {tmp_path / 'out'}" in err
    assert f"(the only copy: move it back to {tmp_path / 'out'})" in err
    assert (aside / "x" / "result.txt").read_text() == "old"
