"""Synthetic FastGO problems with a known answer (tests, benchmarks).

A camera travels ``laps`` times around the same closed route of ``lap_length`` keyframes
(like GC-SLAM's scalability run over a repeated sequence). Each keyframe is registered to its
predecessors (odometry and near-in-time pairs) and to the keyframes at the same place in up to
``loops_per_keyframe`` earlier laps (loop pairs). Correspondences are points seen by keyframe i,
expressed in both frames with optional Gaussian noise. The initial poses integrate the true
odometry with small per-step errors, so they drift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ConfigError
from ..geometry import se3_exp, se3_inverse
from .stats import PairStats

__all__ = ["SyntheticProblem", "loop_route_problem", "make_correspondences"]


@dataclass(frozen=True)
class SyntheticProblem:
    """A pose graph with ground truth.

    Attributes:
        T_gt: (N, 4, 4) float64 true poses (keyframe 0 at its true pose).
        T_init: (N, 4, 4) drifted initial poses (``T_init[0] == T_gt[0]``).
        pairs: (M, 2) int64 keyframe pairs, odometry first.
        stats: statistics of the pairs' correspondences.
        points_i: (M, K, 3) correspondences in frame i (only when requested).
        points_j: (M, K, 3) correspondences in frame j.
    """

    T_gt: Tensor
    T_init: Tensor
    pairs: Tensor
    stats: PairStats
    points_i: Tensor | None = None
    points_j: Tensor | None = None


def make_correspondences(
    T_wc: Tensor, pairs: Tensor, k: int, noise: float, generator: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Sample ``k`` exact-plus-noise correspondences per pair, seen in front of keyframe i.

    Args:
        T_wc: (N, 4, 4) true poses.
        pairs: (M, 2) int64 pairs.
        k: correspondences per pair.
        noise: standard deviation of the Gaussian noise added to each point, metres.
        generator: random source.

    Returns:
        ``(points_i, points_j)``, each (M, k, 3) float64.
    """
    M = pairs.shape[0]
    dt = torch.float64
    u = torch.rand(M, k, 3, generator=generator, dtype=dt)
    p_i = torch.stack([(u[..., 0] - 0.5) * 3.0, (u[..., 1] - 0.5) * 2.0, 1.0 + 3.0 * u[..., 2]], -1)
    T_ji = se3_inverse(T_wc[pairs[:, 1]]) @ T_wc[pairs[:, 0]]
    p_j = (T_ji[:, None, :3, :3] @ p_i[..., None])[..., 0] + T_ji[:, None, :3, 3]
    if noise > 0:
        p_i = p_i + noise * torch.randn(p_i.shape, generator=generator, dtype=dt)
        p_j = p_j + noise * torch.randn(p_j.shape, generator=generator, dtype=dt)
    return p_i, p_j


def loop_route_problem(
    num_keyframes: int,
    lap_length: int | None = None,
    loops_per_keyframe: int = 2,
    local_pairs: int = 2,
    correspondences: int = 32,
    noise: float = 0.0,
    drift_rot: float = 2e-3,
    drift_trans: float = 5e-3,
    keep_points: bool = False,
    seed: int = 0,
) -> SyntheticProblem:
    """Build a repeated-route pose graph with drifted initial poses.

    Args:
        num_keyframes: N.
        lap_length: keyframes per lap (default ``max(N // 4, 8)``: four laps like GC-SLAM's
            repeated fr3/office run).
        loops_per_keyframe: loop pairs to the same place in (randomly chosen) earlier laps.
        local_pairs: extra pairs to keyframes k-2, k-3, ... besides odometry (k-1, k).
        correspondences: correspondences per pair.
        noise: point noise, metres.
        drift_rot: per-step rotation error of the initial odometry, radians (std).
        drift_trans: per-step translation error, metres (std).
        keep_points: also return the raw correspondences.
        seed: seed of the ``torch.Generator``.

    Returns:
        The synthetic problem.
    """
    if num_keyframes < 2:
        raise ConfigError(f"num_keyframes: expected >= 2, got {num_keyframes}")
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    N = num_keyframes
    L = lap_length or max(N // 4, 8)
    k = torch.arange(N, dtype=dt)
    theta = 2 * math.pi * k / L
    radius = max(1.0, 0.25 * L / math.pi)  # about 0.5 m between keyframes
    pos = torch.stack([radius * torch.cos(theta), radius * torch.sin(theta), 0.2 * torch.sin(3 * theta)], -1)
    # Look outwards from the route's centre, with a small per-keyframe wobble.
    yaw = theta + 0.1 * torch.randn(N, generator=g, dtype=dt)
    tw = torch.zeros(N, 6, dtype=dt)
    tw[:, 3:] = 0.05 * torch.randn(N, 3, generator=g, dtype=dt)
    tw[:, 4] += yaw
    T_gt = se3_exp(tw)
    T_gt[:, :3, 3] = pos
    # Camera looks along its z axis: rotate so z points outwards (about x by -90 deg first).
    Rx = se3_exp(torch.tensor([0, 0, 0, -math.pi / 2, 0, 0], dtype=dt))
    T_gt = T_gt @ Rx

    pairs = [torch.stack([torch.arange(0, N - 1), torch.arange(1, N)], -1)]
    for d in range(2, 2 + local_pairs):
        if N > d:
            pairs.append(torch.stack([torch.arange(0, N - d), torch.arange(d, N)], -1))
    if loops_per_keyframe > 0 and N > L:
        kk = torch.arange(L, N)
        laps_back = kk // L  # how many earlier laps exist
        for _ in range(loops_per_keyframe):
            r = torch.rand(kk.shape, generator=g)
            back = 1 + (r * laps_back.to(dt)).floor().to(torch.int64)
            jit = torch.randint(-2, 3, kk.shape, generator=g)
            j = kk - back * L + jit
            ok = (j >= 0) & (j < kk - 1 - local_pairs)
            pairs.append(torch.stack([j[ok], kk[ok]], -1))
    pairs_t = torch.cat(pairs).to(torch.int64)
    # Remove repeated loop pairs (two draws can pick the same earlier keyframe).
    key = pairs_t[:, 0] * N + pairs_t[:, 1]
    _, first = torch.unique(key, return_inverse=True)
    keep = torch.zeros(key.numel(), dtype=torch.bool)
    seen = torch.full((int(first.max()) + 1,), key.numel(), dtype=torch.int64).scatter_reduce(
        0, first, torch.arange(key.numel()), "amin"
    )
    keep[seen] = True
    pairs_t = pairs_t[keep]

    p_i, p_j = make_correspondences(T_gt, pairs_t, correspondences, noise, g)
    stats = PairStats.from_padded(p_i, p_j)

    # Drifted initial poses: true odometry with per-step errors, integrated from keyframe 0.
    T_rel = se3_inverse(T_gt[:-1]) @ T_gt[1:]
    err = torch.cat([drift_trans * torch.randn(N - 1, 3, generator=g, dtype=dt),
                     drift_rot * torch.randn(N - 1, 3, generator=g, dtype=dt)], -1)
    T_rel = T_rel @ se3_exp(err)
    # Prefix product of the relative motions (log N matmul rounds, no loop over keyframes).
    prod = torch.cat([T_gt[:1], T_rel])
    step = 1
    while step < N:
        shifted = torch.cat([torch.eye(4, dtype=dt).expand(step, 4, 4), prod[:-step]])
        prod = shifted @ prod
        step *= 2
    T_init = prod
    return SyntheticProblem(T_gt, T_init, pairs_t, stats, p_i if keep_points else None, p_j if keep_points else None)
