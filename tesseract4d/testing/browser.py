"""Drive the viewer in a real headless Chromium through Playwright: Debian's /usr/bin/chromium,
or the browser named by the environment variable ``TESSERACT4D_CHROMIUM``.

Used by the browser tests and the viewer benchmark. WebGL renders in software (SwiftShader), so a
scene is drawn a few seconds after the page loads; :func:`wait_until_drawn` polls for it.
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Iterator

import numpy as np

CHROMIUM = os.environ.get("TESSERACT4D_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]
# A pixel counts as "drawn" when it differs from the background colour by more than this (0-255).
DRAWN_TOL = 40


@contextlib.contextmanager
def chromium(width: int = 1100, height: int = 700) -> Iterator:
    """Yield a Playwright page in headless Chromium; everything is closed on exit."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            yield page
        finally:
            browser.close()


def canvas_image(page, path: str | None = None) -> np.ndarray:
    """Screenshot of the 3D canvas as (H, W, 3) uint8 RGB (also written to ``path`` if given)."""
    import cv2

    png = page.locator("canvas").first.screenshot(path=path)
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return bgr[..., ::-1].copy()


def drawn_fraction(image: np.ndarray) -> float:
    """Fraction of pixels that differ from the background (the most common border colour)."""
    border = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
    colors, counts = np.unique(border.reshape(-1, 3), axis=0, return_counts=True)
    background = colors[np.argmax(counts)].astype(np.int16)
    diff = np.abs(image.astype(np.int16) - background).max(-1)
    return float((diff > DRAWN_TOL).mean())


def image_change(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of pixels that differ between two screenshots of the same size."""
    return float((np.abs(a.astype(np.int16) - b.astype(np.int16)).max(-1) > DRAWN_TOL).mean())


def wait_until_drawn(page, min_fraction: float = 0.02, timeout_s: float = 60.0, poll_s: float = 0.25) -> tuple[np.ndarray, float]:
    """Poll the canvas until at least ``min_fraction`` of it is drawn; returns (image, seconds)."""
    t0 = time.perf_counter()
    while True:
        try:
            image = canvas_image(page)
        except Exception:  # the canvas does not exist yet
            image = None
        if image is not None and drawn_fraction(image) >= min_fraction:
            return image, time.perf_counter() - t0
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError(f"the canvas showed no scene within {timeout_s:.0f} s")
        time.sleep(poll_s)


def wait_until_changed(page, before: np.ndarray, min_change: float = 0.005, timeout_s: float = 20.0) -> np.ndarray:
    """Poll the canvas until it differs from ``before`` in at least ``min_change`` of its pixels."""
    t0 = time.perf_counter()
    while True:
        image = canvas_image(page)
        if image.shape == before.shape and image_change(image, before) >= min_change:
            return image
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError(f"the canvas did not change within {timeout_s:.0f} s")
        time.sleep(0.25)
