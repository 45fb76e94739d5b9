"""Confidence intervals of success counts, the one definition used by the rollout evaluation
(success per task and arm) and the held-out evaluation (instruction contrast).

``wilson_interval``: the Wilson score interval of a binomial proportion (95 % by default). Unlike
the normal approximation it stays inside [0, 1] and is not empty at 0 or n successes, which is what
small counts such as 5 rollouts or 38 instructions need.
"""

from __future__ import annotations

import math

Z_95 = 1.959963984540054  # two-sided 95 % normal quantile


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (0, 1) when there are no trials."""
    if trials <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be within 0..{trials}, got {successes}")
    p = successes / trials
    z2 = z * z
    denom = 1 + z2 / trials
    centre = (p + z2 / (2 * trials)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials))
    return max(0.0, centre - half), min(1.0, centre + half)
