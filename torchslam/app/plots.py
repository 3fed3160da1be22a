"""Plots of runs: bar charts and top views of trajectories, drawn with matplotlib.

Every figure is drawn with matplotlib's object-oriented API on an Agg canvas, so the global
pyplot state is never touched and no display is needed. matplotlib is imported only when a plot
is drawn.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..data.trajectory import Trajectory
from ..errors import TorchSlamError

__all__ = ["bar_chart", "canvas", "trajectory_image", "trajectory_plot"]


def canvas(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def bar_chart(path: Path, names: list[str], values: list[float], xlabel: str, title: str) -> None:
    fig = canvas(7.0, max(2.0, 0.35 * len(names) + 1.2))
    ax = fig.add_subplot()
    y = list(range(len(names)))
    ax.barh(y, values, color="tab:blue")
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel(xlabel)
    ax.set_title(title)
    ax.grid(axis="x", alpha=0.3)
    for yi, v in zip(y, values):
        ax.annotate(f"{v:.3g}", (v, yi), xytext=(3, 0), textcoords="offset points", va="center", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)


def _trajectory_figure(name: str, estimate: Trajectory, groundtruth: Trajectory | None):
    """Top view of ``estimate`` (aligned onto ``groundtruth`` where possible): ``(figure, caption)``."""
    from ..eval import ate

    p_est = estimate.positions
    caption = "estimate in its own world frame (no ground truth found)"
    p_gt = None
    if groundtruth is not None and len(groundtruth):
        # The ground truth over the estimate's time span only (a run may stop early).
        t0, t1 = float(estimate.timestamps[0]), float(estimate.timestamps[-1])
        keep = (groundtruth.timestamps >= t0 - 0.05) & (groundtruth.timestamps <= t1 + 0.05)
        p_gt = groundtruth.positions[keep]
        try:
            a = ate(estimate, groundtruth, align="se3")
            p_est = p_est @ a.T_align[:3, :3].T + a.T_align[:3, 3]
            caption = f"estimate aligned onto the ground truth (SE(3), {a.matched} poses; ATE RMSE {a.stats['rmse'] * 100:.2f} cm)"
        except TorchSlamError as exc:
            caption = f"estimate unaligned: {exc}"
    ref = p_gt if p_gt is not None and len(p_gt) >= 2 else p_est
    # Top view: look along the axis over which the reference moves least.
    spread = ref.std(dim=0) if len(ref) >= 2 else torch.ones(3, dtype=ref.dtype)
    axes = sorted(int(i) for i in torch.argsort(spread, descending=True)[:2])
    labels = "xyz"
    fig = canvas(5.0, 5.0)
    ax = fig.add_subplot()
    if p_gt is not None and len(p_gt):
        ax.plot(p_gt[:, axes[0]].numpy(), p_gt[:, axes[1]].numpy(), color="0.3", lw=1.5, label="ground truth")
    ax.plot(p_est[:, axes[0]].numpy(), p_est[:, axes[1]].numpy(), color="tab:red", lw=1.2, label="estimate")
    ax.plot([float(p_est[0, axes[0]])], [float(p_est[0, axes[1]])], "o", color="tab:red", ms=4)
    ax.set_xlabel(f"{labels[axes[0]]} (m)")
    ax.set_ylabel(f"{labels[axes[1]]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(name, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig, caption


def trajectory_plot(path: Path, name: str, estimate: Trajectory, groundtruth: Trajectory | None) -> str:
    """Save the top view of ``estimate`` to ``path``; return its caption."""
    fig, caption = _trajectory_figure(name, estimate, groundtruth)
    fig.savefig(path)
    return caption


def trajectory_image(name: str, estimate: Trajectory, groundtruth: Trajectory | None) -> torch.Tensor:
    """The top view of ``estimate`` against ``groundtruth`` as a (3, H, W) float image in [0, 1].

    The same plot as the report's (aligned by SE(3) onto the ground truth where there is one),
    for TensorBoard.
    """
    import numpy as np

    fig, _ = _trajectory_figure(name, estimate, groundtruth)
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    return torch.from_numpy(rgba[..., :3].copy()).permute(2, 0, 1).float() / 255.0
