"""Wilson score intervals on counts worked by hand (rollout success, instruction contrast)."""

from __future__ import annotations

import pytest

from tesseract4d.intervals import wilson_interval

# 95 % Wilson intervals worked by hand to 4 decimals (z = 1.96):
#   p = k/n, d = 1 + z^2/n, centre = (p + z^2/(2n)) / d, half = z/d * sqrt(p(1-p)/n + z^2/(4n^2)).
#   5/10: d = 1.38416, centre = 0.5, half = 1.41600 * sqrt(0.025 + 0.0096040) = 0.26341 -> (0.2366, 0.7634)
#   0/10: centre = half = 0.19208 / 1.38416 = 0.13877 -> (0, 0.2775)
#   1/20: d = 1.19208, centre = 0.14604 / d = 0.12251, half = 1.64419 * sqrt(0.002375 + 0.0024010) = 0.11363 -> (0.0089, 0.2361)
#   50/50: lower = n / (n + z^2) = 50 / 53.8416 = 0.9287, upper 1
KNOWN = [
    (5, 10, 0.2366, 0.7634),
    (0, 10, 0.0, 0.2775),
    (1, 20, 0.0089, 0.2361),
    (50, 50, 0.9287, 1.0),
]


@pytest.mark.parametrize("k,n,lo,hi", KNOWN)
def test_wilson_interval_matches_hand_computed_values(k, n, lo, hi):
    got = wilson_interval(k, n)
    assert got == pytest.approx((lo, hi), abs=1e-4)


def test_wilson_interval_edge_cases():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(3, 2)
