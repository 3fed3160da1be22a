"""Live TensorBoard figures of a run: ATE so far, per-stage milliseconds, keyframes, loops.

One tag scheme for both systems, the step always the frame index (``Frame.index``):
``eval/ate_so_far_m``, ``timing/<stage>_ms``, ``progress/<counter>`` (keyframes, loops, lost or
fused frames; the systems also log ``progress/keyframes`` and ``progress/loops_accepted`` at
each event), ``tracking/<per-frame figure>``, ``optimization/<solver>_ms``, images under
``keyframe/`` and ``trajectory/top_view``.

``progress_callback`` builds the ``on_frame`` hook that :func:`~torchslam.systems.run_sequence`
calls after each frame; every ``every`` frames it asks the system for its current estimate
(``SlamSystem.estimate_so_far``) and logs the ATE of that estimate against the ground truth, the
running per-frame milliseconds of each stage (``stage_ms``) and the system's counters
(``progress_counters``).
``log_final`` adds the top view of the final trajectory against the ground truth as an image.
The work happens outside the compute timer, so frame rates are unaffected apart from wall time.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

from ..data.frame import Sequence
from ..data.trajectory import Trajectory
from ..errors import TorchSlamError
from ..systems.base import SlamSystem, SystemOutput
from ..systems.monitor import Monitor

__all__ = ["log_final", "progress_callback"]

logger = logging.getLogger(__name__)


def _ate_so_far(system: SlamSystem, groundtruth: Trajectory) -> float | None:
    """The headline's ATE (SE(3), evo's association) of the system's current estimate."""
    from ..eval import ate

    estimate = system.estimate_so_far()
    if estimate is None or len(estimate) < 3:
        return None
    try:
        return float(ate(estimate, groundtruth, align="se3").stats["rmse"])
    except TorchSlamError:  # too few matched stamps so far
        return None


def progress_callback(system: SlamSystem, sequence: Sequence, monitor: Monitor, every: int = 30) -> Callable[[int], None]:
    """The ``on_frame`` hook that logs the run's progress every ``every`` frames.

    Logged: ``eval/ate_so_far_m`` (on sequences with ground truth, where ``estimate_so_far()``
    returns an estimate), ``timing/<stage>_ms`` (running mean per processed frame of the
    system's ``stage_ms``), ``progress/<counter>`` (the system's ``progress_counters()``).
    The step is the index of the last frame the system was given (``system.last_frame_index``;
    ``n - 1`` while it is None), as for every figure the systems log themselves.
    """
    # The raw ground truth, as for the headline: the live estimate is at the depth instants,
    # which the ground truth interpolated at the colour stamps does not hold.
    groundtruth = sequence.groundtruth_raw or sequence.groundtruth

    def on_frame(n: int) -> None:
        if every <= 0 or n % every:
            return
        step = n - 1 if system.last_frame_index is None else int(system.last_frame_index)
        if groundtruth is not None:
            value = _ate_so_far(system, groundtruth)
            if value is not None:
                monitor.scalar("eval/ate_so_far_m", value, step)
        monitor.scalars({f"{k}_ms": v / n for k, v in dict(system.stage_ms).items()}, step, prefix="timing/")
        monitor.scalars(system.progress_counters(), step, prefix="progress/")

    return on_frame


def log_hparams(monitor: Monitor, config: dict, metrics: dict) -> None:
    """The run's scalar config values as hparams, with its headline metrics (ATE, frames/s, keyframes)."""
    monitor.hparams(
        {k: v for k, v in config.items() if not isinstance(v, dict)},
        {k: v for k, v in metrics.items() if k in ("ate_rmse_m", "fps_end_to_end", "keyframes") and v is not None},
    )


def log_final(monitor: Monitor, output: SystemOutput, sequence: Sequence, name: str, step: int | None = None) -> None:
    """Log the top view of the final trajectory against the ground truth as an image.

    ``step`` defaults to the index of the last posed frame, the step of every other figure.
    """
    if len(output.T_wc) < 2:
        return
    if step is None:
        step = int(output.frame_indices[-1])
    from .plots import trajectory_image

    estimate = Trajectory(output.timestamps.to(torch.float64), output.T_wc.to(torch.float64))
    try:
        monitor.image("trajectory/top_view", trajectory_image(name, estimate, sequence.groundtruth), step)
    except (TorchSlamError, ValueError) as exc:  # a plot must never cost the run
        logger.warning("trajectory image not logged: %s", exc)
