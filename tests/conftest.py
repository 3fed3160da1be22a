"""Shared test fixtures: the location of the real RGB-D sequences, CUDA marker handling."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tests._helpers import data_root


@pytest.fixture
def shared_data() -> Path:
    """Return the real-data folder, or skip the test saying where it was looked for."""
    root = data_root()
    if not (root / "tum_fr1_xyz" / "rgb.txt").is_file():
        pytest.skip(f"real RGB-D data not found at {root} (set TORCHSLAM_DATA to the folder holding tum_fr1_xyz/)")
    return root


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Run every test on one intra-op thread and restore the setting afterwards.

    Most tests run many small tensor ops; on a 2-core machine that is also running something
    else, two intra-op threads mostly wait on each other and make them several times slower.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)
