"""``app.plots.trajectory_image``: the top view a run logs to TensorBoard, drawn with OpenCV."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchslam.app.plots import _nice_step, _top_view, trajectory_image
from torchslam.data.trajectory import Trajectory
from torchslam.geometry import se3_from_Rt

GT_RGB = np.array([77, 77, 77])
EST_RGB = np.array([214, 39, 40])


def _circle(n: int = 60, radius: float = 0.5, offset=(0.0, 0.0, 0.0)) -> Trajectory:
    a = torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)
    t = torch.stack([radius * a.cos() + offset[0], radius * a.sin() + offset[1], 0.01 * a + offset[2]], 1)
    return Trajectory(torch.arange(n, dtype=torch.float64) / 30, se3_from_Rt(torch.eye(3, dtype=torch.float64).expand(n, 3, 3), t))


def _pixels_of(img: torch.Tensor, rgb: np.ndarray, tol: int = 12) -> np.ndarray:
    """(row, col) of the pixels of colour ``rgb`` inside the plot box, legend and text left out."""
    a = (img.permute(1, 2, 0).numpy() * 255).round().astype(int)
    hit = np.abs(a - rgb).max(-1) <= tol
    inside = np.zeros_like(hit)
    inside[32:453, 64:485] = True  # the box (62..486 x 30..454), its frame excluded
    inside[32:72, 360:485] = False  # the legend
    return np.argwhere(hit & inside)


def test_top_view_draws_both_trajectories_on_equal_scales():
    gt = _circle()
    est = _circle(offset=(3.0, -1.0, 0.2))  # aligned onto the ground truth by SE(3)
    img = trajectory_image("circle", est, gt)
    assert img.shape == (3, 500, 500) and img.dtype == torch.float32
    assert float(img.min()) >= 0 and float(img.max()) <= 1
    red, grey = _pixels_of(img, EST_RGB), _pixels_of(img, GT_RGB)
    assert len(red) > 300 and len(grey) > 150  # the estimate, drawn last, covers part of the ground truth
    # A circle stays a circle (equal scales): the drawn ring's extents in rows and columns agree.
    ring = np.concatenate([red, grey])
    extent = ring.max(0) - ring.min(0)
    assert abs(int(extent[0]) - int(extent[1])) <= 6 and extent.min() > 350  # within the start marker's radius
    # The estimate, drawn 3 m away, was aligned onto the ground truth: its pixels lie on the ring.
    centre, radius = (ring.max(0) + ring.min(0)) / 2, extent.mean() / 2
    off_ring = np.abs(np.linalg.norm(red - centre, axis=1) - radius)
    assert np.percentile(off_ring, 95) <= 4


def test_top_view_without_ground_truth_one_pose_and_non_finite_positions():
    est = _circle(20)
    img = trajectory_image("alone", est, None)
    assert len(_pixels_of(img, EST_RGB)) > 100 and len(_pixels_of(img, GT_RGB, tol=3)) == 0
    one = Trajectory(est.timestamps[:1], est.T_wc[:1])
    assert trajectory_image("one", one, None).shape == (3, 500, 500)  # a point: no line, the start marker
    T = est.T_wc.clone()
    T[5, 0, 3] = math.nan
    T[6, 1, 3] = math.inf
    img = trajectory_image("holes", Trajectory(est.timestamps, T), None)
    assert torch.isfinite(img).all() and len(_pixels_of(img, EST_RGB)) > 100


def test_top_view_looks_along_the_axis_of_least_motion():
    gt = _circle()
    _, _, axes, caption = _top_view(gt, gt)
    assert axes == [0, 1] and "ATE RMSE 0.00 cm" in caption


@pytest.mark.parametrize("span, step", [(1.0, 0.2), (0.37, 0.1), (12.0, 5.0), (0.0042, 0.001), (3.0, 1.0)])
def test_ticks_are_one_two_or_five_times_a_power_of_ten(span, step):
    assert _nice_step(span) == pytest.approx(step)


def test_the_top_view_imports_no_matplotlib():
    # matplotlib's import took about 0.5 s of every run's end, for this one image.
    code = """
import sys, torch
from torchslam.app.plots import trajectory_image
from torchslam.data.trajectory import Trajectory
T = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
T[:, 0, 3] = torch.tensor([0.0, 0.1, 0.3])
trajectory_image("x", Trajectory(torch.arange(3.0, dtype=torch.float64), T), None)
print("matplotlib" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False"]
