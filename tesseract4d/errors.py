"""User-facing errors: the CLI prints their message (which says the fix) without a traceback."""


class UserError(RuntimeError):
    """Bad input or environment that the user can fix; the message tells how."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a scheduler's stop) raised as an interrupt, so every output stage is
    cleaned up as on Ctrl-C (a training run installs its own handler that stops with a checkpoint).
    The command line exits 143 on it."""
