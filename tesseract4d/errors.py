"""User-facing errors: the CLI prints their message (which says the fix) without a traceback."""


class UserError(RuntimeError):
    """Bad input or environment that the user can fix; the message tells how."""
