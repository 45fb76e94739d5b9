"""Option dataclasses saved next to their outputs: one way to write them as JSON and to read a
folder option that takes one folder or several."""

from __future__ import annotations

import dataclasses
from pathlib import Path


def plain(value):
    """``value`` with Paths as strings, inside lists and tuples too (JSON-ready)."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def config_dict(config) -> dict:
    """A dataclass of options as a JSON-ready dict."""
    return {k: plain(v) for k, v in dataclasses.asdict(config).items()}


def folder_list(value) -> list[Path]:
    """One folder, several, or None as a list of Paths."""
    if value is None:
        return []
    return [Path(v) for v in value] if isinstance(value, (list, tuple)) else [Path(value)]
