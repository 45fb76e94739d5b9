"""One colour map for depth and normals: the MP4 previews and the viewer show a depth the same way."""

from __future__ import annotations

import numpy as np

from tesseract4d.colors import DEPTH_PERCENTILES, colorize_depth, depth_range, turbo
from tesseract4d.previews import preview_frames
from viewer.scene import SceneLayer
from reconstruction.backproject import recon_from_episode
from tesseract4d.testing.synthetic_scene import analytic_episode


def test_previews_and_viewer_colour_the_same_depth_alike():
    episode = analytic_episode(num_frames=4, height=40, width=48)
    cam = episode.cameras["base_camera"]
    h, w = cam.depth_m.shape[1:]
    # The preview: RGB | depth | normal, each pixel repeated `scale` times in both directions.
    panel = preview_frames(episode)
    scale = panel.shape[1] // h
    preview_depth = panel[:, :h * scale:scale, w * scale:2 * w * scale:scale]  # (T, H, W, 3)

    # The viewer: the side-panel depth image and the depth colour mode of the points.
    layer = SceneLayer(recon_from_episode(episode), max_points=h * w)
    for t in range(episode.num_frames):
        panel_image = colorize_depth(layer.recon.depth_m[t], *layer.depth_limits)
        np.testing.assert_array_equal(panel_image, preview_depth[t])
        valid = cam.depth_m[t] > 0
        points = layer.colors(layer.frames[t], "depth")  # one point per valid pixel, in pixel order
        assert len(points) == valid.sum()
        # A point's depth comes back from world coordinates: a few points may fall on the other
        # side of a colour level's edge (one level = 1/255 of the range).
        same = np.all(points == preview_depth[t][valid], axis=-1)
        assert same.mean() > 0.99
        assert np.abs(points.astype(int) - preview_depth[t][valid].astype(int)).max() <= 12


def test_near_is_blue_far_is_red_over_the_shared_percentile_range():
    depth = np.linspace(0.5, 2.0, 1000, dtype=np.float32)
    near, far = depth_range(depth)
    np.testing.assert_allclose((near, far), np.percentile(depth, DEPTH_PERCENTILES), rtol=1e-6)
    colours = colorize_depth(np.array([near, far]), near, far)
    assert colours[0, 2] > colours[0, 0] and colours[1, 0] > colours[1, 2]
    np.testing.assert_array_equal(colours, turbo(np.array([0.0, 1.0])))
