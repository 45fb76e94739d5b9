"""Argument types shared by the subcommands: numbers refused at parse time, before any work.

``parser.add_argument("--steps", type=whole(1))`` makes ``--steps 0`` end at once with argparse's
usage line and ``argument --steps: must be a whole number >= 1, got 0`` (exit 2), instead of a
traceback or a silently meaningless run after minutes of sampling.
"""

from __future__ import annotations

import argparse
import math
from typing import Callable

# The seeds numpy and the simulator accept.
MAX_SEED = 2**32 - 1


def whole(low: int, high: int | None = None, hint: str = "") -> Callable[[str], int]:
    """An int in [low, high] (high: no upper bound when None); ``hint`` is appended to the refusal."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (high is not None and value > high):
            span = f">= {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"must be a whole number {span}{hint}, got {text!r}")
        return value

    parse.__name__ = "whole number"  # argparse names the type so in its own messages
    return parse


def number(low: float, *, above: bool = False, high: float | None = None, hint: str = "") -> Callable[[str], float]:
    """A finite float >= low (> low with ``above``) and <= ``high`` when given; ``hint`` is appended
    to the refusal."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or value < low or (above and value == low) or (high is not None and value > high):
            span = f"{'>' if above else '>='} {low:g}" + ("" if high is None else f" and <= {high:g}")
            raise argparse.ArgumentTypeError(f"must be a finite number {span}{hint}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def probability() -> Callable[[str], float]:
    """A share of the time, 0..1."""
    return number(0, high=1)


def seed() -> Callable[[str], int]:
    """A simulator or noise seed: a whole number in 0..2**32-1."""
    return whole(0, MAX_SEED)
