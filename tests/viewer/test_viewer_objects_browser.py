"""The viewer's object layer in a real headless Chromium: a tracked prediction-like source beside the
truth (compare mode); objects drawn whole and named, their paths, the toggle to the raw points, and
the objects moving with the frame slider. Screenshots go to the test artifacts folder."""

from __future__ import annotations

import copy
import time

import numpy as np
import pytest

from tesseract4d.testing.browser import canvas_image, drawn_fraction, image_change, wait_until_changed, wait_until_drawn
from reconstruction.backproject import recon_from_episode
from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still
from test_viewer_browser import click_slider, select, wait_for

pytestmark = pytest.mark.browser
T = 6
HALF = 0.02
RED = np.array([220, 30, 30])


def red_pixels(image: np.ndarray) -> np.ndarray:
    """(N, 2) rows/cols of the canvas's pixels of the red cube's colour (lit or shaded)."""
    img = image.astype(np.int16)
    mask = (img[..., 0] > 120) & (img[..., 1] < 80) & (img[..., 2] < 80)
    return np.argwhere(mask)


@pytest.fixture(scope="module")
def app():
    from viewer.app import ViewerApp

    red = Box("cube_red", moving((-0.04, -0.02, HALF), (0.08, 0.04, HALF), T), np.linspace(0, 0.5, T), (HALF,) * 3, tuple(RED))
    green = Box("cube_green", still((-0.05, -0.1, HALF), T), np.zeros(T), (HALF,) * 3, (30, 200, 40))
    truth = box_episode([red, green], T, size=96, intent={"skill": "push", "target": "cube_red"})
    predicted = copy.deepcopy(truth)
    predicted.source = "prediction"  # tracked through its frames, not read from the recorded poses
    viewer = ViewerApp(recon_from_episode(predicted), compare=recon_from_episode(truth), host="127.0.0.1", port=0)
    viewer.start()
    yield viewer
    viewer.stop()


def test_objects_are_drawn_whole_named_with_their_paths(page, app, artifacts_dir):
    assert app.layer.has_objects and app.right_layer.has_objects
    assert app.layer.recon.objects.source == "segmentation" and app.right_layer.recon.objects.source == "simulator poses"
    # Scene nodes of the object layer: each object, its label and its path; the truth's paths over the prediction.
    assert len(app.layer._object_nodes) == 2 and [l.text for l in app.layer._object_labels] == ["cube_red", "cube_green"]
    handles = app.server.scene._handle_from_node_name
    for name in ("/left/paths/0", "/left/paths/1", "/left/reference/0", "/right/paths/0", "/left/objects/0/points"):
        assert name in handles, name
    image, _ = wait_until_drawn(page, min_fraction=0.05)
    time.sleep(1.0)
    image = canvas_image(page, str(artifacts_dir / "viewer_objects.png"))
    page.screenshot(path=str(artifacts_dir / "viewer_objects_page.png"))
    assert drawn_fraction(image) >= 0.05 and len(red_pixels(image)) >= 20


def test_the_toggle_shows_the_raw_points_instead(page, app, artifacts_dir):
    before = canvas_image(page)
    select(page, "Scene", "Raw points")
    wait_for(lambda: app.scene_dropdown.value == "Raw points")
    after = wait_until_changed(page, before, min_change=0.001)
    canvas_image(page, str(artifacts_dir / "viewer_objects_raw.png"))
    assert "/left/objects/0" not in app.server.scene._handle_from_node_name and image_change(before, after) >= 0.001
    select(page, "Scene", "Object layer")
    wait_for(lambda: app.scene_dropdown.value == "Object layer")
    wait_for(lambda: "/left/objects/0" in app.server.scene._handle_from_node_name)


def test_objects_move_along_their_paths_with_the_frame_slider(page, app, artifacts_dir):
    time.sleep(1.0)
    first = canvas_image(page)
    click_slider(page, "Frame", 0.98)
    wait_for(lambda: app.frame == T - 1)
    last = wait_until_changed(page, first, min_change=0.002)
    time.sleep(0.5)
    last = canvas_image(page, str(artifacts_dir / "viewer_objects_last_frame.png"))
    node = app.layer._object_nodes[0]
    assert np.allclose(node.position, app.layer.recon.objects.tracks[0].T_world_object[-1, :3, 3], atol=1e-6)
    a, b = red_pixels(first), red_pixels(last)
    assert len(a) >= 20 and len(b) >= 20
    assert np.linalg.norm(a.mean(0) - b.mean(0)) > 5.0  # the red cubes moved across the picture (pixels)
