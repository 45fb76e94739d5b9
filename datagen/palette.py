"""The named colours the simulator paints objects with; instructions say their names.

RGBA in [0, 1]. One table for the scene builders (tabletop, ``--randomize-colors``) and the
instruction templates alike.
"""

from __future__ import annotations

COLORS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.1, 0.1, 1.0),
    "green": (0.1, 0.7, 0.15, 1.0),
    "blue": (0.05, 0.16, 0.63, 1.0),
    "yellow": (0.95, 0.85, 0.1, 1.0),
    "purple": (0.5, 0.15, 0.7, 1.0),
    "orange": (1.0, 0.5, 0.05, 1.0),
    "cyan": (0.1, 0.8, 0.85, 1.0),
    "white": (0.95, 0.95, 0.95, 1.0),
}
