"""Bookkeeping both SLAM systems share: the per-frame log against keyframes, and the map's voxel grid.

Both systems pose a frame relative to a keyframe (``T_wc = T_wk[kf] @ T_kf``), so a keyframe
correction (loop closure, pose-graph or global optimisation) moves every frame of that keyframe
without rewriting the log. :class:`FrameLog` records those relative poses with the frame's
stamps, the frames held on a motion prior, and assembles the per-frame part of a
:class:`~torchslam.systems.base.SystemOutput`.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from ..data.frame import Frame
from ..data.trajectory import Trajectory
from .base import SystemOutput, empty_output, frame_poses, resample_poses

__all__ = ["FrameLog", "voxel_downsample"]


class FrameLog:
    """The frames a system has posed, each relative to a keyframe, in the order recorded.

    Attributes (one entry per recorded frame, N in all):
        index: ``Frame.index`` in the sequence.
        time: ``Frame.timestamp`` (the colour stamp the trajectory is reported at), seconds.
        geom_time: ``Frame.geometry_time`` (the depth instant the pose belongs to), seconds.
        kf: the keyframe the pose is relative to; never decreases along the log.
        T_kf: (4, 4) float64 pose of the frame in its keyframe's frame.
        prior: None for a tracked frame, else why its pose is a motion prior (a system's tag:
            NI-SLAM ``"velocity"``; GC-SLAM ``"lost"`` or ``"unlinked"``).
    """

    def __init__(self) -> None:
        self.index: list[int] = []
        self.time: list[float] = []
        self.geom_time: list[float] = []
        self.kf: list[int] = []
        self.T_kf: list[Tensor] = []
        self.prior: list[str | None] = []

    def __len__(self) -> int:
        return len(self.index)

    def record(self, frame: Frame, kf: int, T_kf: Tensor, prior: str | None = None) -> None:
        """Append ``frame`` at ``T_kf`` (4, 4) relative to keyframe ``kf``."""
        self.prior.append(prior)
        self.index.append(frame.index)
        self.time.append(frame.timestamp)
        self.geom_time.append(frame.geometry_time)
        self.kf.append(kf)
        self.T_kf.append(T_kf)

    def hold(self, frame: Frame, prior: str) -> bool:
        """Append ``frame`` at the last recorded pose (a motion prior tagged ``prior``).

        Returns:
            False (and nothing recorded) when the log is empty: there is no pose to hold.
        """
        if not self.index:
            return False
        self.record(frame, self.kf[-1], self.T_kf[-1], prior)
        return True

    def rebase_last(self, kf: int) -> None:
        """The newest recorded frame became keyframe ``kf``: express it relative to itself."""
        self.kf[-1] = kf
        self.T_kf[-1] = torch.eye(4, dtype=torch.float64)

    def poses(self, T_wk: Tensor) -> Tensor:
        """(N, 4, 4) float64 world poses of all frames from the (K, 4, 4) keyframe poses, at the depth instants."""
        return frame_poses(T_wk, self.kf, self.T_kf)

    def so_far(self, T_wk: Tensor) -> Trajectory | None:
        """The frames whose keyframe is among the K of ``T_wk`` (K, 4, 4), at the depth instants.

        The keyframe ids never decrease along the log, so those frames are a prefix of it.
        None when there is none.
        """
        n = bisect.bisect_left(self.kf, len(T_wk))
        if n == 0:
            return None
        T = frame_poses(T_wk, self.kf[:n], self.T_kf[:n])
        return Trajectory(torch.tensor(self.geom_time[:n], dtype=torch.float64), T)

    def at_frame_times(self, T_geom: Tensor, max_gap: float) -> Tensor:
        """Re-sample the (N, 4, 4) poses from the depth instants to the frame (colour) timestamps.

        Linear in translation, SLERP in rotation between neighbouring depth instants; poses
        outside their span or across a gap longer than ``max_gap`` seconds are kept
        (:func:`~torchslam.systems.base.resample_poses`).
        """
        t_geom = torch.tensor(self.geom_time, dtype=torch.float64)
        t_frame = torch.tensor(self.time, dtype=torch.float64)
        return resample_poses(t_geom, T_geom, t_frame, max_gap)

    def n_prior(self) -> int:
        """How many recorded frames are on a motion prior."""
        return sum(p is not None for p in self.prior)

    def prior_indices(self, keep: Callable[[str, int], bool] | None = None) -> Tensor:
        """(M,) int64 sequence indices of the frames on a motion prior.

        Args:
            keep: optional filter on (the frame's prior tag, its keyframe): only frames it
                accepts are listed.
        """
        rows = [f for f, why, kf in zip(self.index, self.prior, self.kf)
                if why is not None and (keep is None or keep(why, kf))]
        return torch.tensor(rows, dtype=torch.int64)

    def output(
        self, T_wc: Tensor, keyframe_indices: list[int], keyframe_T_wc: Tensor, map_points: Tensor | None,
        map_colors: Tensor | None, stage_ms: dict[str, float], metrics: dict[str, Any], prior_indices: Tensor,
    ) -> SystemOutput:
        """The run's output: the log's frame indices and timestamps with the given (N, 4, 4) ``T_wc``."""
        return SystemOutput(
            frame_indices=torch.tensor(self.index, dtype=torch.int64),
            timestamps=torch.tensor(self.time, dtype=torch.float64),
            T_wc=T_wc,
            keyframe_indices=torch.tensor(keyframe_indices, dtype=torch.int64),
            keyframe_T_wc=keyframe_T_wc,
            map_points=map_points,
            map_colors=map_colors,
            stage_ms=stage_ms,
            metrics=metrics,
            prior_indices=prior_indices,
        )

    @staticmethod
    def empty(stage_ms: dict[str, float], metrics: dict[str, Any]) -> SystemOutput:
        """The output of a system that recorded no frame."""
        out = empty_output()
        out.stage_ms = stage_ms
        out.metrics = metrics
        return out


def voxel_downsample(points: torch.Tensor, colors: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Average the points and colours that fall into the same cubic voxel.

    Args:
        points: (P, 3) world points, metres.
        colors: (P, 3) colours in [0, 1].
        voxel: voxel edge, metres (<= 0: no downsampling).

    Returns:
        (points (Q, 3) float32, colors (Q, 3) float32), Q <= P, ordered by voxel key.
    """
    P = points.to(torch.float64)
    C = colors.to(torch.float64)
    if voxel > 0 and len(P):
        # In place where possible: each fresh (P, 3) buffer costs page faults on first touch.
        key = torch.div(P, voxel).floor_().to(torch.int64)
        # One int64 per voxel, ordered as the (x, y, z) rows lexicographically: a 1-D unique is
        # much cheaper than ``unique(dim=0)`` over rows.
        key -= key.min(0).values
        span = key.max(0).values + 1
        if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:
            flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
            _, inv = torch.unique(flat, return_inverse=True)
        else:
            _, inv = torch.unique(key, dim=0, return_inverse=True)
        n = int(inv.max()) + 1
        cnt = torch.zeros(n, dtype=torch.float64, device=P.device).index_add_(0, inv, torch.ones_like(P[:, 0]))
        P = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, P) / cnt[:, None]
        C = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, C) / cnt[:, None]
    return P.float(), C.float()
