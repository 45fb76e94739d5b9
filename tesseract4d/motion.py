"""What counts as motion in an RGB-D clip: one set of tolerances for evaluation's "moving"
region and the dynamic points of a back-projected episode.

A pixel's depth has changed when it differs from a reference depth by more than
``MOVING_DEPTH_TOL_M`` plus ``MOVING_DEPTH_TOL_REL`` of the reference (sensor and codec noise
grow with depth); its colour has changed when any channel differs by more than ``MOVING_RGB_TOL``.
"""

from __future__ import annotations

import numpy as np

MOVING_RGB_TOL = 20  # 0-255, any channel
MOVING_DEPTH_TOL_M = 0.01
MOVING_DEPTH_TOL_REL = 0.01


def depth_tolerance_m(reference_m: np.ndarray, tol_m: float = MOVING_DEPTH_TOL_M,
                      tol_rel: float = MOVING_DEPTH_TOL_REL) -> np.ndarray:
    """The depth change (metres, same shape as ``reference_m``) above which a pixel has moved."""
    return tol_m + tol_rel * np.asarray(reference_m)
