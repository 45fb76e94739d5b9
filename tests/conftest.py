"""Shared test set-up: the same runtime environment as the CLI, and an artifacts folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tesseract4d import runtime

runtime.configure()

ARTIFACTS_DIR = Path(os.environ.get("TESSERACT4D_TEST_ARTIFACTS", Path(__file__).resolve().parent.parent / "test-artifacts"))


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    """A folder for files a person may want to look at after the run (screenshots, previews)."""
    ARTIFACTS_DIR.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS_DIR
