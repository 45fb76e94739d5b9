"""MP4 previews: two futures of one scene side by side, each under its caption."""

from __future__ import annotations

import numpy as np
import pytest

from tesseract4d.testing.synthetic_scene import analytic_episode
from tesseract4d.colors import depth_range
from tesseract4d.previews import preview_frames, side_by_side_frames, write_side_by_side


def test_side_by_side_puts_each_future_under_its_caption():
    a, b = analytic_episode(num_frames=4, height=32, width=32, seed=0), analytic_episode(num_frames=3, height=32, width=32, seed=2)
    frames = side_by_side_frames([a, b], ["push the box to the right", "keep still"])
    single = preview_frames(a)  # (T, H', W', 3)
    band = frames.shape[1] - single.shape[1]
    assert frames.shape == (4, band + single.shape[1], 2 * single.shape[2], 3) and frames.dtype == np.uint8
    assert band > 0 and band % 16 == 0 and frames.shape[2] % 16 == 0
    # Below the bands: the two previews with one shared depth range; the shorter one holds its last frame.
    limits = depth_range(np.concatenate([a.cameras["base_camera"].depth_m.ravel(), b.cameras["base_camera"].depth_m.ravel()]))
    w = single.shape[2]
    np.testing.assert_array_equal(frames[:, band:, :w], preview_frames(a, depth_limits=limits))
    np.testing.assert_array_equal(frames[:, band:, w:], preview_frames(b, depth_limits=limits)[[0, 1, 2, 2]])
    # Each band carries text (bright pixels), the same in every frame.
    for half in (frames[:, :band, :w], frames[:, :band, w:]):
        assert (half[0] > 200).any() and (half == half[:1]).all()
    assert not np.array_equal(frames[0, :band, :w], frames[0, :band, w:])


def test_long_captions_wrap_and_mismatched_inputs_are_refused():
    a = analytic_episode(num_frames=2, height=32, width=32)
    short = side_by_side_frames([a, a], ["a", "b"])
    long = side_by_side_frames([a, a], ["a", " ".join(["push the red cube to the left"] * 6)])
    assert long.shape[1] > short.shape[1] and long.shape[2] == short.shape[2]
    with pytest.raises(ValueError, match="one caption per episode"):
        side_by_side_frames([a, a], ["only one"])
    with pytest.raises(ValueError, match="one resolution"):
        side_by_side_frames([a, analytic_episode(num_frames=2, height=32, width=48)], ["a", "b"])


def test_side_by_side_mp4_opens_with_opencv(tmp_path):
    import cv2

    a, b = analytic_episode(num_frames=5, height=32, width=32, seed=0), analytic_episode(num_frames=5, height=32, width=32, seed=3)
    path = write_side_by_side(tmp_path / "pair.mp4", [a, b], ["left future", "right future"])
    cap = cv2.VideoCapture(str(path))
    try:
        count, width = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    finally:
        cap.release()
    assert count == 5 and width == 2 * preview_frames(a).shape[2]
    assert [p.name for p in tmp_path.iterdir()] == ["pair.mp4"]  # no temporary file left
