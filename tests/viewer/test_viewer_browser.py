"""The viewer in a real headless Chromium: the cloud is drawn, the GUI drives it, export plays.

One server and one browser page are shared by the tests of this module (in file order), on a
small saved Recon4D: a table plane and a box sliding across the view, 6 frames.
Screenshots go to the test artifacts folder.
"""

from __future__ import annotations

import time

import pytest

from reconstruction.recon4d import Recon4D
from tesseract4d.testing.browser import canvas_image, drawn_fraction, image_change, wait_until_changed, wait_until_drawn
from reconstruction.backproject import recon_from_episode
from tesseract4d.testing.synthetic_scene import analytic_episode

pytestmark = pytest.mark.browser
NUM_FRAMES = 6


def back_projecting_generator(instruction: str, seed: int, steps: int, progress) -> Recon4D:
    """A real (model-free) generator: renders the analytic scene for this seed and back-projects it,
    reporting progress once per 'step'."""
    for step in range(steps):
        progress(0.8 * (step + 1) / steps, f"step {step + 1}/{steps}")
    if instruction == "fail":
        raise RuntimeError("the sampler diverged (requested by the test)")
    return recon_from_episode(analytic_episode(num_frames=NUM_FRAMES, height=64, width=64, seed=seed, instruction=instruction))


@pytest.fixture(scope="module")
def recon_dir(tmp_path_factory):
    recon = recon_from_episode(analytic_episode(num_frames=NUM_FRAMES, height=80, width=80))
    return recon.save(tmp_path_factory.mktemp("viewer") / "recon")


@pytest.fixture(scope="module")
def app(recon_dir):
    from viewer.app import ViewerApp
    from viewer.sources import load_source

    viewer = ViewerApp(load_source(recon_dir), host="127.0.0.1", port=0, generate=back_projecting_generator)
    viewer.start()
    yield viewer
    viewer.stop()


def control(page, label: str):
    """The GUI element labelled ``label`` (viser renders <label for=ID> next to each input)."""
    label_el = page.locator("label", has_text=label).first
    by_id = page.locator(f'[id="{label_el.get_attribute("for")}"]')
    if by_id.count():
        return by_id
    # Text inputs get their own id; take the input in the label's row.
    return label_el.locator("xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]//input").first


def click_slider(page, label: str, fraction: float) -> None:
    box = control(page, label).bounding_box()
    page.mouse.click(box["x"] + fraction * box["width"], box["y"] + box["height"] / 2)


def select(page, label: str, option: str) -> None:
    control(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()


def wait_for(condition, timeout_s: float = 20.0) -> None:
    t0 = time.perf_counter()
    while not condition():
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError("condition not reached")
        time.sleep(0.1)


def test_canvas_shows_the_point_cloud(page, artifacts_dir):
    image, seconds = wait_until_drawn(page, min_fraction=0.05)
    time.sleep(0.5)  # let the frustum texture arrive too
    canvas_image(page, str(artifacts_dir / "viewer_frame0.png"))
    page.screenshot(path=str(artifacts_dir / "viewer_page.png"))
    assert drawn_fraction(image) >= 0.05, f"only {drawn_fraction(image):.3f} of the canvas is drawn"


def test_frame_slider_changes_the_picture(page, app, artifacts_dir):
    before = canvas_image(page)
    click_slider(page, "Frame", 0.98)
    wait_for(lambda: app.frame_slider.value == NUM_FRAMES - 1 == app.frame)
    after = wait_until_changed(page, before)
    canvas_image(page, str(artifacts_dir / "viewer_last_frame.png"))
    assert image_change(before, after) > 0.005


def test_colour_mode_changes_the_picture(page, app, artifacts_dir):
    before = wait_until_drawn(page)[0]
    select(page, "Colour", "Normal")
    wait_for(lambda: app.color_dropdown.value == "Normal")
    after = wait_until_changed(page, before, min_change=0.02)
    canvas_image(page, str(artifacts_dir / "viewer_normals.png"))
    assert image_change(before, after) > 0.02
    select(page, "Colour", "Static / dynamic")
    wait_for(lambda: app.color_dropdown.value == "Static / dynamic")
    wait_until_changed(page, after, min_change=0.02)
    canvas_image(page, str(artifacts_dir / "viewer_dynamic.png"))


def test_play_advances_frames(page, app):
    seen = set()
    page.get_by_label("Play", exact=True).check()
    t0 = time.perf_counter()
    while len(seen) < 3 and time.perf_counter() - t0 < 10:
        seen.add(app.frame)
        time.sleep(0.05)
    page.get_by_label("Play", exact=True).uncheck()
    assert len(seen) >= 3, f"playback showed only frames {sorted(seen)}"
    wait_for(lambda: app.frame_slider.value == app.frame)  # paused: the slider shows the exact frame


def test_generate_panel_shows_the_result_and_errors(page, app, artifacts_dir):
    before = wait_until_drawn(page)[0]
    text = control(page, "Instruction")
    text.fill("fail")
    text.press("Enter")
    wait_for(lambda: app.instruction_text.value == "fail")
    page.get_by_role("button", name="Generate").click()
    page.get_by_text("Generation failed").first.wait_for(timeout=20_000)
    assert "sampler diverged" in (app.generation_error or "")
    assert app.server is not None and app.generation_count == 0  # still serving

    # One input at a time, as a person types: viser's client sends all GUI updates through one
    # 50 ms throttle that keeps only the latest message, so two inputs changed within 50 ms of
    # the Generate click would lose the first of them.
    text.fill("slide the box further")
    text.press("Enter")
    wait_for(lambda: app.instruction_text.value == "slide the box further")
    seed = control(page, "Seed")
    seed.fill("4")
    seed.press("Enter")
    wait_for(lambda: app.seed_number.value == 4)
    page.get_by_role("button", name="Generate").click()
    page.get_by_text("Done:").first.wait_for(timeout=30_000)
    assert app.generation_count == 1 and app.layer.recon.metadata["instruction"] == "slide the box further"
    after = wait_until_changed(page, before, min_change=0.005)
    page.screenshot(path=str(artifacts_dir / "viewer_generated_page.png"))
    assert image_change(before, after) > 0.005


def test_exported_html_renders_from_file(recon_dir, tmp_path, page, artifacts_dir):
    from viewer.export import export_html

    html = export_html(Recon4D.load(recon_dir), tmp_path / "scene.html")
    p = page.context.browser.new_page(viewport=page.viewport_size)  # same browser, no server involved
    try:
        p.goto(html.resolve().as_uri())
        image, _ = wait_until_drawn(p, min_fraction=0.05)
        first = canvas_image(p, str(artifacts_dir / "viewer_export.png"))
        # The recording plays: the picture changes as frames are switched.
        changed = wait_until_changed(p, first, min_change=0.002)
        canvas_image(p, str(artifacts_dir / "viewer_export_later.png"))
    finally:
        p.close()
    assert drawn_fraction(image) >= 0.05 and image_change(first, changed) >= 0.002
