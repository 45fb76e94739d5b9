"""Static compositing: the given first frame put back where a predicted clip is still."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tesseract4d.model.static_composite import STATIC_MARGIN_PX, composite_static, dilate_max, stillness


def _clip(seed: int, b: int = 1, t: int = 5, c: int = 7, h: int = 24, w: int = 24) -> torch.Tensor:
    """A predicted clip whose frames equal its frame 0 up to a small jitter everywhere."""
    g = torch.Generator().manual_seed(seed)
    frame0 = torch.rand(b, 1, c, h, w, generator=g) * 1.6 - 0.8
    return frame0 + (torch.rand(b, t, c, h, w, generator=g) - 0.5) * 0.02


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), tolerance=st.floats(0.05, 0.5))
def test_a_still_clip_becomes_the_first_frame_and_a_moved_block_stays_as_predicted(seed, tolerance):
    clip = _clip(seed)
    g = torch.Generator().manual_seed(seed + 1)
    first = (clip[:, 0] + (torch.rand(clip[:, 0].shape, generator=g) - 0.5) * 0.2).clamp(-1, 1)
    moved = clip.clone()
    moved[:, 2:, 3, 8:14, 8:14] += 2 * tolerance  # something moves into one block from frame 2 on
    out = composite_static(moved, first, tolerance)
    # Every frame of a still clip (jitter 0.01 < tolerance / 2) is the first frame, frame 0 included.
    torch.testing.assert_close(composite_static(clip, first, tolerance), first[:, None].expand_as(clip))
    torch.testing.assert_close(out[:, :2], first[:, None].expand(-1, 2, -1, -1, -1))
    # The moved block and its margin are left exactly as predicted; far from it the first frame shows.
    lo, hi = 8 - STATIC_MARGIN_PX, 14 + STATIC_MARGIN_PX
    assert torch.equal(out[:, 2:, :, lo:hi, lo:hi], moved[:, 2:, :, lo:hi, lo:hi].clamp(-1, 1))
    torch.testing.assert_close(out[:, 2:, :, :, :lo - 1], first[:, None, :, :, :lo - 1].expand(-1, 3, -1, -1, -1))
    assert out.min() >= -1 and out.max() <= 1


def test_stillness_ramps_from_half_the_tolerance_to_the_tolerance():
    clip = torch.zeros(1, 2, 1, 9, 9)
    for change, expected in ((0.05, 1.0), (0.1, 1.0), (0.15, 0.5), (0.2, 0.0), (0.4, 0.0)):
        clip[:, 1] = change
        m = stillness(clip, 0.2, margin_px=0)
        assert torch.allclose(m[:, 0], torch.ones(1, 9, 9)) and torch.allclose(m[:, 1], torch.full((1, 9, 9), expected))
    # One changed pixel makes its neighbours within the margin count as changed too.
    clip = torch.zeros(1, 2, 1, 9, 9)
    clip[0, 1, 0, 4, 4] = 1.0
    m = stillness(clip, 0.2, margin_px=2)[0, 1]
    assert (m[2:7, 2:7] == 0).all() and m.sum() == 81 - 25


def test_bad_input_is_refused():
    clip = _clip(0)
    with pytest.raises(ValueError, match="tolerance must be > 0"):
        composite_static(clip, clip[:, 0], 0.0)
    with pytest.raises(ValueError, match="first_frame must be"):
        composite_static(clip, clip[:, 0, :3], 0.1)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), radius=st.integers(0, 4), h=st.integers(1, 12), w=st.integers(1, 12))
def test_dilate_max_is_a_stride_1_max_pool(seed, radius, h, w):
    import torch.nn.functional as F

    x = torch.randn(2, 3, h, w, generator=torch.Generator().manual_seed(seed))
    assert torch.equal(dilate_max(x, radius), F.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius))
    # A window wider than the image sees all of it.
    assert torch.equal(dilate_max(x, max(h, w)), x.amax(dim=(-2, -1), keepdim=True).expand_as(x))
