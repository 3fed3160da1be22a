"""Loop-closure acceptance by global registration error (GC-SLAM, paper §IV-C).

A true loop closure only tightens the pose estimates; after re-optimisation the registration
error of the pairs accepted so far hardly changes. A false loop bends the map, and the pairs
accepted so far then fit worse. So: add the candidate pairs, re-optimise, and keep them only
if the cost per correspondence of the previously accepted pairs has not grown by more than
``threshold`` (the paper's 5 %); otherwise roll back poses and pairs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ShapeError, check_shape
from .linearize import _pair_cost
from .optimize import FastGOConfig, FastGOProblem, FastGOResult, PairStatus, optimize_batch, pair_status
from .stats import PairStats

__all__ = ["LoopDecision", "accept_loop_closures", "accept_loop_closures_batch"]


@dataclass(frozen=True)
class LoopDecision:
    """Outcome of one loop-closure test.

    Attributes:
        accepted: whether the candidate pairs were kept.
        T_wc: (N, 4, 4) float64 poses to continue from: the re-optimised poses if accepted,
            otherwise the poses given (rolled back).
        pairs: (M', 2) the accepted pair set (old pairs, plus the candidates if accepted).
        stats: statistics of ``pairs``.
        cost_before: cost per correspondence of the previously accepted pairs at the given
            poses, square metres.
        cost_after: the same after re-optimising with the candidates.
        result: the trial optimisation with the candidates.
    """

    accepted: bool
    T_wc: Tensor
    pairs: Tensor
    stats: PairStats
    cost_before: float
    cost_after: float
    result: FastGOResult


def _cost_per_correspondence(T: Tensor, problem: FastGOProblem, config: FastGOConfig) -> Tensor:
    status = pair_status(problem.pairs, problem.stats, problem.T_wc.shape[0], config.min_correspondences, config.collinear_tol)
    use = (status == int(PairStatus.OK)).to(torch.float64)
    stats = problem.stats.to(dtype=torch.float64)
    if problem.pair_weights is not None:
        stats = stats.weighted(problem.pair_weights.to(torch.float64))
    cost = torch.where(use > 0, _pair_cost(T.to(torch.float64), problem.pairs, stats), torch.zeros_like(use))
    n = torch.where(use > 0, stats.n, torch.zeros_like(use)).sum()
    return cost.sum() / n.clamp_min(torch.finfo(torch.float64).tiny)


def accept_loop_closures_batch(
    problems: Sequence[FastGOProblem],
    candidates: Sequence[tuple[Tensor, PairStats]],
    threshold: float = 0.05,
    config: FastGOConfig | None = None,
    min_cost: float = 1e-12,
) -> list[LoopDecision]:
    """Test candidate loop pairs for B problems at once (one batched re-optimisation).

    Args:
        problems: B current problems; their poses should be the optimum of their pairs (as
            after every GC-SLAM keyframe insertion).
        candidates: B tuples ``(loop_pairs (L_b, 2) int64, loop_stats)``.
        threshold: allowed relative growth of the previously accepted pairs' cost per
            correspondence (paper: 5 %).
        config: optimiser settings.
        min_cost: absolute slack in square metres, so noise-free problems (cost ~ 0) are
            judged by round-off rather than by a ratio of zeros.

    Returns:
        B decisions; each problem is accepted or rolled back on its own.
    """
    if len(candidates) != len(problems):
        raise ShapeError(f"candidates: expected {len(problems)} entries like problems, got {len(candidates)}")
    config = config or FastGOConfig()
    trials = []
    for m, (p, (lp, ls)) in enumerate(zip(problems, candidates)):
        check_shape(lp, f"{len(ls)} 2", f"candidates[{m}] pairs")
        w = None
        if p.pair_weights is not None:
            w = torch.cat([p.pair_weights, torch.ones(len(ls), dtype=p.pair_weights.dtype, device=p.pair_weights.device)])
        trials.append(FastGOProblem(p.T_wc, torch.cat([p.pairs, lp.to(p.pairs.device)]), PairStats.cat([p.stats, ls.to(p.stats.device, p.stats.dtype)]), p.fixed, w))
    batch = optimize_batch(trials, config)
    decisions = []
    for b, (p, (lp, ls)) in enumerate(zip(problems, candidates)):
        res = batch.problem(b)
        before = _cost_per_correspondence(p.T_wc, p, config)
        after = _cost_per_correspondence(res.T_wc, p, config)
        ok = bool(after <= before * (1 + threshold) + min_cost)
        decisions.append(
            LoopDecision(
                accepted=ok,
                T_wc=res.T_wc if ok else p.T_wc.to(torch.float64),
                pairs=trials[b].pairs if ok else p.pairs,
                stats=trials[b].stats if ok else p.stats,
                cost_before=float(before),
                cost_after=float(after),
                result=res,
            )
        )
    return decisions


def accept_loop_closures(
    T_wc: Tensor,
    pairs: Tensor,
    stats: PairStats,
    loop_pairs: Tensor,
    loop_stats: PairStats,
    fixed: int = 0,
    threshold: float = 0.05,
    config: FastGOConfig | None = None,
    min_cost: float = 1e-12,
) -> LoopDecision:
    """Add candidate loop pairs, re-optimise, and keep them only if the map stays consistent.

    Args:
        T_wc: (N, 4, 4) current keyframe poses (the optimum of ``pairs``).
        pairs: (M, 2) int64 accepted pairs.
        stats: their statistics.
        loop_pairs: (L, 2) int64 candidate loop pairs.
        loop_stats: their statistics.
        fixed: gauge keyframe.
        threshold: allowed relative growth of the accepted pairs' cost per correspondence.
        config: optimiser settings.
        min_cost: absolute slack, square metres.

    Returns:
        The decision, with the poses and pairs to continue from.
    """
    return accept_loop_closures_batch(
        [FastGOProblem(T_wc, pairs, stats, fixed)], [(loop_pairs, loop_stats)], threshold, config, min_cost
    )[0]
