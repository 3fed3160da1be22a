"""Plots of runs: bar charts and top views of trajectories.

The report's figures are drawn with matplotlib's object-oriented API on an Agg canvas, so the
global pyplot state is never touched and no display is needed; matplotlib is imported only when
such a plot is drawn. The top view that every run logs to TensorBoard (``trajectory_image``) is
drawn with OpenCV instead: importing matplotlib cost each run's end about 0.5 s.
"""

from __future__ import annotations

import math
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


def _top_view(estimate: Trajectory, groundtruth: Trajectory | None):
    """``(p_est, p_gt, axes, caption)``: the estimate's positions (aligned by SE(3) onto the ground
    truth where possible), the ground truth's over the estimate's time span (or None), and the two
    axes of the top view (the reference moves least along the third)."""
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
    return p_est, p_gt, axes, caption


def _trajectory_figure(name: str, estimate: Trajectory, groundtruth: Trajectory | None):
    """Top view of ``estimate`` (aligned onto ``groundtruth`` where possible): ``(figure, caption)``."""
    p_est, p_gt, axes, caption = _top_view(estimate, groundtruth)
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


# Colours of the OpenCV top view (RGB), as the matplotlib one's: grey ground truth, tab:red estimate.
_GT_RGB = (77, 77, 77)
_EST_RGB = (214, 39, 40)
_GRID_RGB = (225, 225, 225)
_TEXT_RGB = (40, 40, 40)


def _nice_step(span: float, ticks: int = 5) -> float:
    """A tick spacing of 1, 2 or 5 times a power of ten giving about ``ticks`` ticks over ``span``."""
    raw = span / ticks
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw)


def trajectory_image(name: str, estimate: Trajectory, groundtruth: Trajectory | None, size: int = 500) -> torch.Tensor:
    """The top view of ``estimate`` against ``groundtruth`` as a (3, size, size) float image in [0, 1].

    The report's plot (aligned by SE(3) onto the ground truth where there is one, the same axes),
    drawn with OpenCV for TensorBoard at the end of every run: importing matplotlib took about
    0.5 s of each run's end. Equal scales on both axes, a grid at 1, 2 or 5 times a power of ten
    metres, the start marked; positions that are not finite are left out.
    """
    import cv2
    import numpy as np

    p_est, p_gt, axes, _ = _top_view(estimate, groundtruth)
    labels = "xyz"
    est = p_est[:, axes].to(torch.float64).numpy()
    gt = p_gt[:, axes].to(torch.float64).numpy() if p_gt is not None and len(p_gt) else np.zeros((0, 2))
    est, gt = est[np.isfinite(est).all(1)], gt[np.isfinite(gt).all(1)]
    img = np.full((size, size, 3), 255, np.uint8)
    left, right, top, bottom = 62, 14, 30, 46
    w, h = size - left - right, size - top - bottom
    pts = np.concatenate([est, gt]) if len(est) + len(gt) else np.zeros((1, 2))
    lo, hi = pts.min(0), pts.max(0)
    span = max(float((hi - lo).max()) * 1.08, 1e-3)  # equal scales: the larger extent fills the box
    x0, y0 = (lo + hi) / 2 - span / 2
    scale = min(w, h) / span  # pixels per metre

    def to_px(p: np.ndarray) -> np.ndarray:
        u = left + (p[:, 0] - x0) * scale
        v = top + h - (p[:, 1] - y0) * scale  # y up
        return np.round(np.stack([u, v], 1) * 16).astype(np.int32)  # 4 fractional bits (shift=4)

    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    step = _nice_step(span)
    for axis in (0, 1):
        start = (x0, y0)[axis]
        for k in range(math.ceil(start / step), math.floor((start + span) / step) + 1):
            value = k * step
            text = f"{value:.10g}"
            if axis == 0:
                u = int(round(left + (value - x0) * scale))
                cv2.line(img, (u, top), (u, top + h), _GRID_RGB, 1)
                (tw, _), _ = cv2.getTextSize(text, font, fs, 1)
                cv2.putText(img, text, (u - tw // 2, top + h + 16), font, fs, _TEXT_RGB, 1, cv2.LINE_AA)
            else:
                v = int(round(top + h - (value - y0) * scale))
                cv2.line(img, (left, v), (left + w, v), _GRID_RGB, 1)
                (tw, th), _ = cv2.getTextSize(text, font, fs, 1)
                cv2.putText(img, text, (left - tw - 6, v + th // 2), font, fs, _TEXT_RGB, 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (left + w, top + h), _TEXT_RGB, 1)
    if len(gt) >= 2:
        cv2.polylines(img, [to_px(gt)], False, _GT_RGB, 2, cv2.LINE_AA, shift=4)
    if len(est) >= 2:
        cv2.polylines(img, [to_px(est)], False, _EST_RGB, 1, cv2.LINE_AA, shift=4)
    if len(est):
        cv2.circle(img, tuple(int(c) for c in to_px(est[:1])[0]), 4 * 16, _EST_RGB, -1, cv2.LINE_AA, shift=4)
    xlabel, ylabel = f"{labels[axes[0]]} (m)", f"{labels[axes[1]]} (m)"
    (tw, _), _ = cv2.getTextSize(xlabel, font, 0.45, 1)
    cv2.putText(img, xlabel, (left + (w - tw) // 2, size - 10), font, 0.45, _TEXT_RGB, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, top - 10), font, 0.45, _TEXT_RGB, 1, cv2.LINE_AA)
    title = name if len(name) <= 48 else name[:45] + "..."
    (tw, _), _ = cv2.getTextSize(title, font, 0.45, 1)
    cv2.putText(img, title, (left + max(0, (w - tw) // 2), 18), font, 0.45, _TEXT_RGB, 1, cv2.LINE_AA)
    entries = ([("ground truth", _GT_RGB, 2)] if len(gt) else []) + [("estimate", _EST_RGB, 1)]
    for i, (text, colour, thick) in enumerate(entries):  # the legend, top right inside the box
        v = top + 14 + 16 * i
        u = left + w - 120
        cv2.line(img, (u, v - 4), (u + 22, v - 4), colour, thick, cv2.LINE_AA)
        cv2.putText(img, text, (u + 28, v), font, fs, _TEXT_RGB, 1, cv2.LINE_AA)
    return torch.from_numpy(img).permute(2, 0, 1).float() / 255.0
