"""Real-image fixtures for the KCC tests: frames of ``tum_fr1_xyz`` read directly with OpenCV."""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

# TUM freiburg1 preset and depth scale (see the sequence's SOURCE.md).
FR1_INTRINSICS = (517.3, 516.5, 318.6, 255.3)
DEPTH_SCALE = 5000.0


def _listed(path: Path) -> list[str]:
    return [line.split()[1] for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


@functools.lru_cache(maxsize=8)
def load_tum_frame(root: str, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the index-th colour (H, W, 3) uint8 RGB and depth (H, W) float32 metres of tum_fr1_xyz.

    Colour and depth of the same list index are 15–35 ms apart; good enough for these tests,
    which plant their own motion.
    """
    seq = Path(root) / "tum_fr1_xyz"
    rgb = cv2.imread(str(seq / _listed(seq / "rgb.txt")[index]), cv2.IMREAD_COLOR)
    depth = cv2.imread(str(seq / _listed(seq / "depth.txt")[index]), cv2.IMREAD_UNCHANGED)
    assert rgb is not None and depth is not None, f"cannot read frame {index} of {seq}"
    return cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB), depth.astype(np.float32) / DEPTH_SCALE


@pytest.fixture
def tum_rgbd(shared_data):
    """(rgb (1, 3, 480, 640) float32 in [0, 1], depth (1, 1, 480, 640) metres, intrinsics (4,)) of frame 0."""
    rgb, depth = load_tum_frame(str(shared_data), 0)
    return (
        torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0,
        torch.from_numpy(depth)[None, None],
        torch.tensor(FR1_INTRINSICS),
    )


@pytest.fixture
def grey_patches(shared_data):
    """(2, 128, 128) float64 grey images in [0, 1]: centre crops of frames 0 and 150, area-resized."""
    out = []
    for index in (0, 150):
        rgb, _ = load_tum_frame(str(shared_data), index)
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[48:432, 128:512]  # 384 x 384 centre
        out.append(cv2.resize(grey, (128, 128), interpolation=cv2.INTER_AREA))
    return torch.from_numpy(np.stack(out)).double() / 255.0
