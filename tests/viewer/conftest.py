"""Shared set-up of the viewer's browser tests: one headless Chromium page per test module, on the
module's own ``app`` fixture (a started ViewerApp)."""

from __future__ import annotations

import pytest

from tesseract4d.testing.browser import chromium


@pytest.fixture(scope="module")
def page(app):
    with chromium() as p:
        p.goto(app.url)
        yield p
