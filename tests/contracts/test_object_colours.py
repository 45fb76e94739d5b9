"""min_colour_distance: the nearest palette colour's RGB distance, as the direct definition gives it."""

import numpy as np
import pytest

from tesseract4d.object_colours import OBJECT_COLOUR_TOL, min_colour_distance


def _direct(colours, palette):
    diff = np.asarray(colours, np.float64)[:, None, :] - np.asarray(palette, np.float64)[None, :, :]
    return np.sqrt((diff**2).sum(-1)).min(axis=1)


@pytest.mark.parametrize("n,m", [(1, 1), (37, 5), (4000, 96), (600, 5000)])
def test_integer_colours_are_exact(n, m):
    rng = np.random.default_rng(n + m)
    colours = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    palette = rng.integers(0, 256, (m, 3)).astype(np.float32)
    got = min_colour_distance(colours, palette)
    assert got.dtype == np.float32 and got.shape == (n,)
    np.testing.assert_allclose(got, _direct(colours, palette), rtol=1e-6, atol=1e-4)
    # the tolerance test every caller makes is exact on integer colours
    np.testing.assert_array_equal(got < OBJECT_COLOUR_TOL, _direct(colours, palette) < OBJECT_COLOUR_TOL)


def test_float_colours_and_empty_inputs():
    rng = np.random.default_rng(1)
    colours, palette = rng.uniform(0, 255, (300, 3)), rng.uniform(0, 255, (20, 3))
    np.testing.assert_allclose(min_colour_distance(colours, palette), _direct(colours, palette), atol=1e-3)
    assert np.isinf(min_colour_distance(colours[:3], np.zeros((0, 3)))).all()
    assert min_colour_distance(np.zeros((0, 3)), palette).shape == (0,)
    assert min_colour_distance([[10, 20, 30]], [[10, 20, 30]])[0] == 0.0
