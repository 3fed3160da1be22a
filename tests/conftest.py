"""Shared test fixtures: the location of the real RGB-D sequences, CUDA marker handling."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]


def data_root() -> Path:
    """Folder of the real sequences: ``$TORCHSLAM_DATA`` or ``../shared/data`` beside the repo."""
    env = os.environ.get("TORCHSLAM_DATA")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data")


@pytest.fixture
def shared_data() -> Path:
    """Return the real-data folder, or skip the test saying where it was looked for."""
    root = data_root()
    if not (root / "tum_fr1_xyz" / "rgb.txt").is_file():
        pytest.skip(f"real RGB-D data not found at {root} (set TORCHSLAM_DATA to the folder holding tum_fr1_xyz/)")
    return root


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)
