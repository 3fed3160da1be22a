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
from ..geometry.lie import se3_exp, se3_inverse, se3_log
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

    And per keyframe ``k`` that :meth:`link` described, ``links[k]``: the keyframe it was linked
    to when it was made and that link's pose (``T_ref_k``, as tracked), for :meth:`poses`'
    ``spread``.
    """

    def __init__(self) -> None:
        self.index: list[int] = []
        self.time: list[float] = []
        self.geom_time: list[float] = []
        self.kf: list[int] = []
        self.T_kf: list[Tensor] = []
        self.prior: list[str | None] = []
        self.links: dict[int, tuple[int, Tensor]] = {}

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

    def link(self, kf: int, reference: int | None, T_ref: Tensor | None) -> None:
        """Keyframe ``kf`` was placed by tracking at ``T_ref`` (4, 4) in keyframe ``reference``
        (None: unlinked, nothing recorded)."""
        if reference is not None and T_ref is not None:
            self.links[kf] = (int(reference), T_ref.detach().to("cpu", torch.float64))

    def poses(self, T_wk: Tensor, spread: bool = False) -> Tensor:
        """(N, 4, 4) float64 world poses of all frames from the (K, 4, 4) keyframe poses, at the depth instants.

        ``spread``: the frames between keyframe ``a`` and the next one, ``b``, where ``b`` was
        linked to ``a`` when it was made (:meth:`link`), follow the correction the keyframe
        poses made to that link, in proportion to their time from ``a`` to ``b``. A frame is
        tracked against ``a`` alone, so ``T_wk[a] @ T_kf`` places it by ``a``'s correction only,
        while the optimisation (a loop, a link measured again) may have moved ``b`` otherwise
        relative to ``a``: the same frame reached through ``b``, ``T_wk[b] @ T_ref_b^-1 @ T_kf``,
        differs by that change. The frame takes the geodesic between the two, in its own axes (a
        rotation turns it about itself), at the fraction ``(t - t_a) / (t_b - t_a)`` of its depth
        instant, with ``t_a`` and ``t_b`` the keyframes' own instants (their first rows in the
        log, where both must be). Keyframes keep their poses (fraction 0); frames of the last keyframe, of
        a keyframe whose successor was linked to another (a relocalisation) or unlinked, and
        keyframes the optimisation left as tracked are unchanged (the two ways agree).
        """
        return self._poses(T_wk, len(self), spread)

    def _poses(self, T_wk: Tensor, n: int, spread: bool) -> Tensor:
        """:meth:`poses` of the first ``n`` frames, whose keyframes are all among ``T_wk``."""
        if not spread or not self.links or not n:
            return frame_poses(T_wk, self.kf[:n], self.T_kf[:n])
        dev, K = T_wk.device, T_wk.shape[0]
        kf_of = torch.tensor(self.kf[:n], dtype=torch.int64)
        T_kf = torch.stack(self.T_kf[:n]).to(T_wk)
        T = T_wk[kf_of.to(dev)] @ T_kf
        # The keyframes a whose successor b = a + 1 was linked to a, both with a frame of their own
        # in the log (a keyframe's first row: the ids never decrease along it).
        first = torch.searchsorted(kf_of, torch.arange(K))
        logged = (first < len(kf_of)) & (kf_of[first.clamp(max=len(kf_of) - 1)] == torch.arange(K))
        nxt = [a for a in range(K - 1) if bool(logged[a] & logged[a + 1]) and self.links.get(a + 1, (None,))[0] == a]
        if not nxt:
            return T
        slot = torch.full((K,), -1, dtype=torch.int64)
        slot[torch.tensor(nxt)] = torch.arange(len(nxt))
        rows = (slot[kf_of] >= 0).nonzero().flatten()  # the frames to spread
        s = slot[kf_of[rows]]  # each one's keyframe among ``nxt``
        t_geom = torch.tensor(self.geom_time[:n], dtype=torch.float64)
        a_of = torch.tensor(nxt)
        t_a, t_b = t_geom[first[a_of]], t_geom[first[a_of + 1]]
        T_ref_inv = se3_inverse(torch.stack([self.links[a + 1][1] for a in nxt])).to(T_wk)
        span = (t_b - t_a)[s]
        frac = torch.where(span > 0, (t_geom[rows] - t_a[s]) / torch.where(span > 0, span, 1.0), 0.0).clamp(0.0, 1.0)
        rows_d = rows.to(dev)
        T1 = T[rows_d]
        T2 = T_wk[kf_of[rows].to(dev) + 1] @ T_ref_inv[s.to(dev)] @ T_kf[rows_d]
        out = T.clone()
        out[rows_d] = T1 @ se3_exp(se3_log(se3_inverse(T1) @ T2) * frac.to(T1)[:, None])
        return out

    def so_far(self, T_wk: Tensor, spread: bool = False) -> Trajectory | None:
        """The frames whose keyframe is among the K of ``T_wk`` (K, 4, 4), at the depth instants
        (``spread``: as :meth:`poses`, over the links among those keyframes).

        The keyframe ids never decrease along the log, so those frames are a prefix of it.
        None when there is none.
        """
        n = bisect.bisect_left(self.kf, len(T_wk))
        if n == 0:
            return None
        T = self._poses(T_wk, n, spread)
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
