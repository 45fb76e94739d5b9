"""How a long run stops on a signal: after the step it is in, keeping its work, then saying so.

A training loop runs inside :class:`StopSignals`: SIGTERM (a scheduler's stop, ``kill``) and Ctrl-C
then only ask it to stop; it finishes its step, writes its checkpoint and export, and the command
line ends with :func:`raise_for_stop`, so the exit status still tells a stopped run (143, 130) from
a finished one (0).
"""

from __future__ import annotations

import contextlib
import signal
import threading

from tesseract4d.errors import Terminated


class StopSignals:
    """Within the block, SIGTERM and SIGINT set ``requested`` (and ``signum``, the first one) instead
    of stopping the process; the handlers before are restored on exit. Signals are only handled in
    the main thread; elsewhere the block changes nothing."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.requested = False
        self.signum: int | None = None
        self._previous: dict = {}

    def _request(self, signum, frame) -> None:
        self.requested = True
        self.signum = self.signum or signum

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._request) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> bool:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        return False


def raise_for_stop(signum: int | None) -> None:
    """End a command that stopped on a signal as that signal would have: Terminated (exit 143) for
    SIGTERM, KeyboardInterrupt (exit 130) for SIGINT; nothing when it was not stopped."""
    if signum == signal.SIGTERM:
        raise Terminated()
    if signum == signal.SIGINT:
        raise KeyboardInterrupt()


@contextlib.contextmanager
def handlers_kept():
    """Put this process's SIGTERM and SIGINT handlers back after a block that installs its own
    (``ray.init()`` does, with a stack dump and exit 1 on SIGTERM), so the command line's stop still
    applies. Main thread only; a handler set outside Python (None) is left as the block left it."""
    saved = ({s: signal.getsignal(s) for s in StopSignals.SIGNALS}
             if threading.current_thread() is threading.main_thread() else {})
    try:
        yield
    finally:
        for s, handler in saved.items():
            if handler is not None:
                signal.signal(s, handler)
