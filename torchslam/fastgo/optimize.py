"""FastGO global optimisation: Gauss-Newton / Levenberg-Marquardt over all keyframe poses.

Minimises FastGO Eq. (1), ``sum_pairs sum_k w |T_i p_i^k - T_j p_j^k|^2``, from per-pair
statistics only (see :mod:`torchslam.fastgo.linearize`): every iteration costs O(#pairs) to
linearise plus one block-sparse Cholesky solve (:mod:`torchslam.optim.blocksparse`). Near the
optimum the residual curvature, also O(#pairs) from the statistics, turns the Gauss-Newton steps
into Newton steps (``FastGOConfig.newton``); large graphs with noisy pairs otherwise crawl along
their soft bending modes for many iterations.

Beyond the paper, an optional robust variant re-weights whole pairs by their RMS residual
(IRLS with Huber, Cauchy, Geman-McClure or Tukey kernels): a robust norm cannot act on single
correspondences once they are summarised, but it can act on pairs, so one wrong loop pair
cannot bend the map.

Input problems are sanitised first, and what was done is reported in the result:

* pairs with fewer than ``min_correspondences`` correspondences (or zero weight), pairs whose
  points are collinear in either frame and pairs with non-finite statistics are excluded;
* repeated keyframe pairs (either orientation) are merged into their first occurrence;
* keyframes not connected to the gauge by valid pairs are reported as ``disconnected``; each
  such connected part is optimised with its own lowest keyframe held fixed;
* a pair ``(i, i)`` or an index outside ``[0, N)`` raises :class:`~torchslam.errors.ShapeError`.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from ..errors import (
    AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, ShapeError, check_float, check_limits, check_shape, parse_choice,
)
from ..optim.blocksparse import Schedule, SolverMethod
from ..optim.graphs import adjacency, connected_components
from ..optim.lm import LMConfig, levenberg_marquardt_se3
from ..optim.robust import RobustKernel, robust_weight
from .linearize import PairLinearization, _blocks, _centred, _pair_cost, assemble
from .stats import PairStats

__all__ = [
    "PairStatus",
    "FastGOConfig",
    "FastGOProblem",
    "FastGOResult",
    "FastGOBatchResult",
    "pair_status",
    "optimize",
    "optimize_batch",
]

log = logging.getLogger(__name__)


class PairStatus(enum.IntEnum):
    """Why a pair was used or left out (``FastGOResult.pair_status``)."""

    OK = 0
    TOO_FEW = 1  # fewer than min_correspondences correspondences, or no weight
    COLLINEAR = 2  # points (nearly) on a line in frame i or j: a rotation is unobservable
    NONFINITE = 3  # NaN or inf in the statistics
    DUPLICATE = 4  # same keyframe pair as an earlier one; merged into it


@dataclass(frozen=True)
class FastGOConfig:
    """FastGO optimiser settings.

    Attributes:
        iterations: maximum LM iterations per robust round (GC-SLAM runs 3 per keyframe with loop candidates).
        tol: stop when a step lowers (or is predicted to lower) the cost by at most
            ``tol * cost``.
        step_tol: stop when no pose moves by more than this (metres / radians). A negative
            ``tol`` or ``step_tol`` turns that test off.
        damping: initial Levenberg-Marquardt factor (0: start as pure Gauss-Newton).
        solver: linear solver, a :class:`~torchslam.optim.SolverMethod` or its name.
        leaf_size: supernode size of the sparse Cholesky analysis, in keyframes.
        ordering: fill-reducing order of the sparse Cholesky, ``"band"`` (reverse
            Cuthill-McKee, suits route-like graphs) or ``"nested"`` (nested dissection).
        schedule: how the sparse Cholesky walks its elimination tree, ``"front"`` (one
            supernode at a time; fastest on the CPU) or ``"level"`` (batched over each level:
            fewer calls on accelerators, where ``ordering="nested"`` makes the tree shallow).
        line_search: extend accepted steps along their direction when the cost keeps falling
            (see :class:`~torchslam.optim.LMConfig`).
        newton: near the optimum, add the residual curvature of the exponential map (also
            O(#pairs) from the statistics, :func:`~torchslam.fastgo.residual_curvature`) to
            ``J^T J``: Newton instead of Gauss-Newton steps, which removes the slow linear tail
            on soft modes of large graphs with noisy correspondences.
        robust: pair re-weighting kernel (:class:`~torchslam.optim.RobustKernel` or its name);
            ``l2`` turns re-weighting off.
        robust_scale: kernel scale on the per-pair RMS residual, metres.
        robust_rounds: maximum IRLS rounds (the first round is unweighted).
        robust_tol: stop re-weighting when no pair weight changes by more than this.
        min_correspondences: pairs with fewer correspondences are excluded.
        collinear_tol: a pair is collinear when the second invariant of its centred point
            scatter (``l1 l2 + l1 l3 + l2 l3`` of its eigenvalues) is below ``collinear_tol``
            times ``trace^2``, in frame i or j (about ``l2 < collinear_tol * l1``).
    """

    iterations: int = 20
    tol: float = 1e-6
    step_tol: float = 1e-10
    damping: float = 1e-6
    solver: SolverMethod | str = SolverMethod.AUTO
    leaf_size: int = 16
    ordering: str = "band"
    schedule: Schedule | str = Schedule.FRONT
    line_search: bool = True
    newton: bool = True
    robust: RobustKernel | str = RobustKernel.L2
    robust_scale: float = 0.05
    robust_rounds: int = 10
    robust_tol: float = 1e-3
    min_correspondences: int = 3
    collinear_tol: float = 1e-9

    LIMITS: ClassVar[dict[str, Limit]] = {
        "iterations": NON_NEGATIVE, "tol": Limit(), "step_tol": Limit(), "damping": NON_NEGATIVE,
        "leaf_size": AT_LEAST_1, "robust_scale": POSITIVE, "robust_rounds": AT_LEAST_1, "robust_tol": NON_NEGATIVE,
        "min_correspondences": Limit(ge=3), "collinear_tol": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver", SolverMethod.parse(self.solver))
        object.__setattr__(self, "schedule", parse_choice(Schedule, self.schedule, "schedule"))
        object.__setattr__(self, "robust", RobustKernel.parse(self.robust))
        check_limits(self)

    def lm(self) -> LMConfig:
        """The Levenberg-Marquardt settings of one round."""
        return LMConfig(
            iterations=self.iterations, tol=self.tol, step_tol=self.step_tol, damping=self.damping,
            solver=self.solver, leaf_size=self.leaf_size, ordering=self.ordering, schedule=self.schedule,
            line_search=self.line_search, newton=self.newton,
        )


@dataclass(frozen=True)
class FastGOProblem:
    """One pose-graph problem: keyframe poses and the statistics of registered pairs.

    Attributes:
        T_wc: (N, 4, 4) initial keyframe poses, camera to world.
        pairs: (M, 2) int64 keyframe indices (i, j).
        stats: statistics of the M pairs, points in frames i and j.
        fixed: index of the keyframe held fixed (gauge).
        pair_weights: optional (M,) non-negative pair weights (may require grad).
    """

    T_wc: Tensor
    pairs: Tensor
    stats: PairStats
    fixed: int = 0
    pair_weights: Tensor | None = None

    def __post_init__(self) -> None:
        d: dict[str, int] = {}
        check_shape(self.T_wc, "N 4 4", "T_wc", d)
        check_float(self.T_wc, "T_wc")
        check_shape(self.pairs, f"{len(self.stats)} 2", "pairs")
        if self.pairs.dtype != torch.int64:
            raise ShapeError(f"pairs: expected int64 keyframe indices, got {self.pairs.dtype}")
        n = d["N"]
        if not 0 <= int(self.fixed) < n:
            raise ShapeError(f"fixed: expected a keyframe index in [0, {n}), got {self.fixed}")
        if self.pair_weights is not None:
            check_shape(self.pair_weights, f"{len(self.stats)}", "pair_weights")


@dataclass(frozen=True)
class FastGOResult:
    """Outcome of :func:`optimize`.

    Attributes:
        T_wc: (N, 4, 4) float64 optimised poses.
        cost: (I + 1,) float64 objective before the first and after each iteration (robust
            rounds concatenated; each round's objective uses that round's pair weights).
        iterations: LM iterations run (all rounds).
        converged: True when the last round met the tolerance and the weights settled.
        time_s: wall time, seconds.
        pair_status: (M,) int8 :class:`PairStatus` of each input pair.
        pair_weights: (M,) final robust weights (1 without re-weighting; 0 for excluded or
            merged pairs).
        pair_rms: (M,) RMS residual per correspondence at the result, metres (NaN for
            excluded pairs; a merged duplicate reports its merged pair's value).
        disconnected: (N,) bool, keyframes not linked to the gauge by valid pairs.
    """

    T_wc: Tensor
    cost: Tensor
    iterations: int
    converged: bool
    time_s: float
    pair_status: Tensor
    pair_weights: Tensor
    pair_rms: Tensor
    disconnected: Tensor


@dataclass(frozen=True)
class FastGOBatchResult:
    """Outcome of :func:`optimize_batch` for B problems (fields concatenated over problems).

    Attributes:
        T_wc: (sum N, 4, 4) optimised poses; problem b is ``node_offsets[b]:node_offsets[b+1]``.
        cost: (B, I + 1) per-problem objective history (flat after a problem stopped).
        iterations: (B,) int64.
        converged: (B,) bool.
        time_s: wall time of the whole batch, seconds.
        pair_status, pair_weights, pair_rms: (sum M,) as in :class:`FastGOResult`.
        disconnected: (sum N,) bool.
        node_offsets: (B + 1,) int64.
        pair_offsets: (B + 1,) int64.
    """

    T_wc: Tensor
    cost: Tensor
    iterations: Tensor
    converged: Tensor
    time_s: float
    pair_status: Tensor
    pair_weights: Tensor
    pair_rms: Tensor
    disconnected: Tensor
    node_offsets: Tensor
    pair_offsets: Tensor

    def __len__(self) -> int:
        return self.converged.shape[0]

    def problem(self, b: int) -> FastGOResult:
        """Return problem ``b``'s result."""
        n0, n1 = int(self.node_offsets[b]), int(self.node_offsets[b + 1])
        m0, m1 = int(self.pair_offsets[b]), int(self.pair_offsets[b + 1])
        return FastGOResult(
            self.T_wc[n0:n1], self.cost[b], int(self.iterations[b]), bool(self.converged[b]), self.time_s,
            self.pair_status[m0:m1], self.pair_weights[m0:m1], self.pair_rms[m0:m1], self.disconnected[n0:n1],
        )


# ----------------------------------------------------------------------------------------------


def pair_status(
    pairs: Tensor, stats: PairStats, num_nodes: int, min_correspondences: int = 3, collinear_tol: float = 1e-9
) -> Tensor:
    """Classify pairs as usable or degenerate (duplicates are not detected here).

    Args:
        pairs: (M, 2) int64 keyframe indices.
        stats: statistics of the M pairs.
        num_nodes: N keyframes.
        min_correspondences: fewer correspondences than this is ``TOO_FEW``.
        collinear_tol: relative eigenvalue threshold of ``COLLINEAR``.

    Returns:
        (M,) int8 :class:`PairStatus` codes.

    Raises:
        ShapeError: for a pair (i, i) or an index outside [0, N).
    """
    check_shape(pairs, f"{len(stats)} 2", "pairs")
    if pairs.numel():
        bad = (pairs < 0) | (pairs >= num_nodes)
        if bool(bad.any()):
            m = int(torch.nonzero(bad.any(-1))[0, 0])
            raise ShapeError(f"pairs: row {m} = {pairs[m].tolist()} is outside [0, {num_nodes})")
        same = pairs[:, 0] == pairs[:, 1]
        if bool(same.any()):
            m = int(torch.nonzero(same)[0, 0])
            raise ShapeError(f"pairs: row {m} pairs keyframe {int(pairs[m, 0])} with itself")
    st = stats.to(dtype=torch.float64)
    vec = st.as_vector()
    finite = torch.isfinite(vec).all(-1)
    status = torch.full((len(stats),), int(PairStatus.OK), dtype=torch.int8, device=pairs.device)
    few = (stats.count < min_correspondences) | ~(st.n > 0)
    safe = torch.where(finite[:, None], vec, torch.zeros_like(vec))
    safe[:, 0] = torch.where(few | ~finite, torch.ones_like(safe[:, 0]), safe[:, 0])
    _, _, C_ii, _, C_jj = PairStats.from_vector(safe, stats.count).centred()

    def flat(C: Tensor) -> Tensor:
        # Points on a line leave a scatter of rank <= 1: its second invariant
        # I2 = (tr(C)^2 - tr(C^2)) / 2 = l1 l2 + l1 l3 + l2 l3 vanishes against tr(C)^2.
        tr = torch.diagonal(C, dim1=-2, dim2=-1).sum(-1)
        i2 = 0.5 * (tr * tr - (C * C.transpose(-1, -2)).sum((-1, -2)))
        return i2 <= collinear_tol * (tr * tr).clamp_min(torch.finfo(C.dtype).tiny)

    line = flat(C_ii) | flat(C_jj)
    status = torch.where(line, torch.full_like(status, int(PairStatus.COLLINEAR)), status)
    status = torch.where(few, torch.full_like(status, int(PairStatus.TOO_FEW)), status)
    status = torch.where(~finite, torch.full_like(status, int(PairStatus.NONFINITE)), status)
    return status


@dataclass
class _Work:
    """The flattened, sanitised batch the LM iterations run on."""

    T: Tensor  # (N, 4, 4) float64
    node_problem: Tensor  # (N,)
    fixed: Tensor  # (N,) bool
    disconnected: Tensor  # (N,) bool
    pairs: Tensor  # (W, 2) working pairs
    stats: PairStats  # (W,) merged statistics, user weights applied
    pair_problem: Tensor  # (W,)
    work_of_input: Tensor  # (M,) working index of each input pair, -1 if excluded
    status: Tensor  # (M,) int8
    num_problems: int
    node_offsets: Tensor
    pair_offsets: Tensor
    extra: dict = field(default_factory=dict)


def _prepare(problems: Sequence[FastGOProblem], config: FastGOConfig) -> _Work:
    if len(problems) == 0:
        raise ShapeError("problems: expected at least one FastGOProblem, got none")
    dev = problems[0].T_wc.device
    B = len(problems)
    n_sizes = [p.T_wc.shape[0] for p in problems]
    m_sizes = [len(p.stats) for p in problems]
    node_offsets = torch.tensor([0] + n_sizes, dtype=torch.int64).cumsum(0)
    pair_offsets = torch.tensor([0] + m_sizes, dtype=torch.int64).cumsum(0)
    status = torch.cat(
        [
            pair_status(p.pairs, p.stats, n, config.min_correspondences, config.collinear_tol).to(dev)
            for p, n in zip(problems, n_sizes)
        ]
    )
    T = torch.cat([p.T_wc.to(torch.float64) for p in problems])
    pairs = torch.cat([p.pairs.to(dev) + int(o) for p, o in zip(problems, node_offsets[:-1])])
    weights = torch.cat(
        [
            p.pair_weights.to(dev, torch.float64) if p.pair_weights is not None
            else torch.ones(len(p.stats), dtype=torch.float64, device=dev)
            for p in problems
        ]
    )
    stats = PairStats.cat([p.stats.to(dev, torch.float64) for p in problems])
    node_problem = torch.repeat_interleave(torch.arange(B, device=dev), torch.tensor(n_sizes, device=dev))
    Ntot = T.shape[0]

    # Merge repeated keyframe pairs (either orientation) into their first occurrence.
    ok = status == int(PairStatus.OK)
    idx_ok = torch.nonzero(ok)[:, 0]
    p_ok = pairs[idx_ok]
    lo, hi = p_ok.min(-1).values, p_ok.max(-1).values
    key = lo * Ntot + hi
    uniq, inverse = torch.unique(key, return_inverse=True)
    pos = torch.arange(idx_ok.numel(), device=dev)
    first = torch.full((uniq.numel(),), idx_ok.numel(), dtype=torch.int64, device=dev).scatter_reduce(
        0, inverse, pos, "amin"
    )
    is_first = first[inverse] == pos
    dup_input = idx_ok[~is_first]
    status = status.clone()
    status[dup_input] = int(PairStatus.DUPLICATE)
    # Orient every member like its group's first pair, weight it, and sum the group.
    flip = p_ok[:, 0] != p_ok[first[inverse], 0]
    st_ok = stats[idx_ok].weighted(weights[idx_ok])
    st_sw = st_ok.swapped()
    vec = torch.where(flip[:, None], st_sw.as_vector(), st_ok.as_vector())
    cnt = st_ok.count
    merged_vec = vec.new_zeros(uniq.numel(), 28).index_add(0, inverse, vec)
    merged_cnt = cnt.new_zeros(uniq.numel()).index_add(0, inverse, cnt)
    work_stats = PairStats.from_vector(merged_vec, merged_cnt)
    work_pairs = p_ok[first]
    work_of_input = torch.full((pairs.shape[0],), -1, dtype=torch.int64, device=dev)
    work_of_input[idx_ok] = inverse

    # Connectivity: every connected part gets a gauge; parts without the user's gauge are
    # reported as disconnected and held by their lowest keyframe.
    wp = work_pairs.detach().cpu().numpy()
    _, labels = connected_components(adjacency(Ntot, wp[:, 0], wp[:, 1]))
    gauge_nodes = np.array([int(o) + int(p.fixed) for p, o in zip(problems, node_offsets[:-1])])
    labels_t = torch.as_tensor(labels, device=dev)
    gauge_label = labels_t[torch.as_tensor(gauge_nodes, device=dev)]
    disconnected = labels_t != gauge_label[node_problem]
    first_of_label = np.full(labels.max() + 1, Ntot, dtype=np.int64)
    np.minimum.at(first_of_label, labels, np.arange(Ntot))
    fixed = torch.zeros(Ntot, dtype=torch.bool, device=dev)
    fixed[torch.as_tensor(gauge_nodes, device=dev)] = True
    fixed[disconnected & (torch.arange(Ntot, device=dev) == torch.as_tensor(first_of_label, device=dev)[labels_t])] = True
    if bool(disconnected.any()):
        log.info("fastgo: %d keyframes are not connected to their gauge", int(disconnected.sum()))
    excluded = int((status != int(PairStatus.OK)).sum())
    if excluded:
        log.info("fastgo: %d pairs excluded or merged (see pair_status)", excluded)
    return _Work(
        T=T, node_problem=node_problem, fixed=fixed, disconnected=disconnected, pairs=work_pairs,
        stats=work_stats, pair_problem=node_problem[work_pairs[:, 0]], work_of_input=work_of_input,
        status=status, num_problems=B, node_offsets=node_offsets.to(dev), pair_offsets=pair_offsets.to(dev),
    )


def _run(work: _Work, config: FastGOConfig):
    B, N = work.num_problems, work.T.shape[0]
    pairs, pp = work.pairs, work.pair_problem
    T = work.T
    robust_w = torch.ones(len(work.stats), dtype=torch.float64, device=T.device)
    histories, iters, converged = [], torch.zeros(B, dtype=torch.int64, device=T.device), None
    symbolic = None
    lm_cfg = config.lm()
    for rnd in range(config.robust_rounds):
        stats = work.stats if rnd == 0 else work.stats.weighted(robust_w)

        cen = _centred(stats, T.dtype)
        if rnd == 0:
            work.extra["centred"] = cen  # the unweighted statistics, reused by _rms

        def lin(T_: Tensor, stats=stats, cen=cen):
            out = _blocks(T_, pairs, stats, with_curvature=config.newton)
            (H_ii, H_ij, H_jj), g_i = out[0], out[1]
            H, g = assemble(PairLinearization(H_ii, H_ij, H_jj, g_i, -g_i, g_i[:, 0]), pairs, N)

            def cost() -> Tensor:
                # Lazy: the optimiser only reads it at the start point; later it already has
                # the cost of the accepted poses from evaluate().
                return evaluate(T_)

            if not config.newton:
                return H, g, cost
            curvatures = out[3]

            def S() -> Tensor:
                S_i, S_j = curvatures()
                return S_i.new_zeros(N, 6, 6).index_add(0, pairs[:, 0], S_i).index_add(0, pairs[:, 1], S_j)

            return H, g, cost, S

        def evaluate(T_: Tensor, stats=stats, cen=cen):
            c = _pair_cost(T_, pairs, stats, cen)
            return c.new_zeros(B).index_add(0, pp, c)

        if symbolic is None and lm_cfg.solver in (SolverMethod.AUTO, SolverMethod.CHOLESKY):
            from ..optim.blocksparse import analyze

            symbolic = analyze(N, pairs[:, 0], pairs[:, 1], work.fixed, 6, config.leaf_size, config.ordering)
        res = levenberg_marquardt_se3(T, work.node_problem, B, lin, evaluate, work.fixed, lm_cfg, symbolic)
        T = res.T
        histories.append(res.cost if rnd == 0 else res.cost[:, 1:])
        iters = iters + res.iterations
        converged = res.converged
        if config.robust is RobustKernel.L2:
            break
        rms = _rms(T, work)
        new_w = robust_weight(rms, config.robust, config.robust_scale)
        change = (new_w - robust_w).detach().abs()
        ch_p = torch.zeros(B, dtype=change.dtype, device=T.device).scatter_reduce(0, pp, change, "amax")
        robust_w = new_w
        settled = ch_p <= config.robust_tol
        if bool(settled.all()):
            converged = converged & settled
            break
        converged = converged & settled
    return T, torch.cat(histories, dim=1), iters, converged, robust_w


def _rms(T: Tensor, work: _Work) -> Tensor:
    c = _pair_cost(T, work.pairs, work.stats, work.extra.get("centred"))
    n = work.stats.n
    return torch.where(n > 0, c / torch.where(n > 0, n, torch.ones_like(n)), torch.zeros_like(n)).sqrt()


def optimize_batch(problems: Sequence[FastGOProblem], config: FastGOConfig | None = None) -> FastGOBatchResult:
    """Optimise B independent pose graphs of different sizes in one flattened system.

    The problems share every tensor operation and one block-diagonal sparse solve, but each
    has its own damping, step acceptance and convergence test.

    Args:
        problems: B problems.
        config: optimiser settings (defaults when None).

    Returns:
        Concatenated per-problem results; ``.problem(b)`` slices one out.
    """
    start = time.perf_counter()
    config = config or FastGOConfig()
    work = _prepare(problems, config)
    T, cost, iters, converged, robust_w = _run(work, config)
    widx = work.work_of_input
    W = robust_w.shape[0]
    # Excluded pairs read a trailing slot: weight 0, RMS NaN.
    slot = torch.where(widx >= 0, widx, torch.full_like(widx, W))
    ok = work.status == int(PairStatus.OK)
    pair_w = torch.where(ok, torch.cat([robust_w, robust_w.new_zeros(1)])[slot], robust_w.new_zeros(()))
    rms = _rms(T, work)
    pair_rms = torch.cat([rms, rms.new_full((1,), float("nan"))])[slot]
    return FastGOBatchResult(
        T_wc=T, cost=cost, iterations=iters, converged=converged, time_s=time.perf_counter() - start,
        pair_status=work.status, pair_weights=pair_w, pair_rms=pair_rms, disconnected=work.disconnected,
        node_offsets=work.node_offsets, pair_offsets=work.pair_offsets,
    )


def optimize(
    T_wc: Tensor,
    pairs: Tensor,
    stats: PairStats,
    fixed: int = 0,
    config: FastGOConfig | None = None,
    pair_weights: Tensor | None = None,
    **overrides,
) -> FastGOResult:
    """Optimise keyframe poses from pair statistics (FastGO, paper §III).

    Args:
        T_wc: (N, 4, 4) initial keyframe poses, camera to world.
        pairs: (M, 2) int64 keyframe indices (i, j).
        stats: statistics of the M pairs (points in frames i and j).
        fixed: keyframe held fixed (gauge).
        config: optimiser settings; ``overrides`` replace single fields
            (``optimize(..., iterations=3, tol=1e-6)``).
        pair_weights: optional (M,) pair weights; gradients flow from the result poses to
            them through the unrolled iterations.

    Returns:
        Optimised float64 poses, cost history and the per-pair / per-keyframe report.
    """
    config = config or FastGOConfig()
    if overrides:
        import dataclasses

        try:
            config = dataclasses.replace(config, **overrides)
        except TypeError as err:
            valid = ", ".join(f.name for f in dataclasses.fields(FastGOConfig))
            raise ConfigError(f"optimize: unknown option in {sorted(overrides)}; valid: {valid}") from err
    res = optimize_batch([FastGOProblem(T_wc, pairs, stats, fixed, pair_weights)], config)
    return res.problem(0)
