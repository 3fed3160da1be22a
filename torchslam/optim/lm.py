"""Batched Levenberg-Marquardt on SE(3) poses with block-sparse normal equations.

One call optimises B independent problems whose poses are concatenated into one ``(N, 4, 4)``
tensor (``node_problem`` says which problem each pose belongs to). Each problem has its own
damping, its own accept/reject decision and its own convergence test, never a batch mean;
a converged problem takes zero steps while the others go on.

Convention:
    Updates are left-multiplicative, ``T <- se3_exp(delta) @ T``, with twists ``(rho, phi)``.
    The caller's ``linearize`` must return the Gauss-Newton system in that parameterisation:
    ``H = J^T J``, ``g = J^T r`` and cost ``r^T r`` summed per problem, and may add the
    residual-curvature blocks ``S`` of the exact Hessian ``H + S``.

Beyond plain Levenberg-Marquardt: an accepted step is extended along its direction when a
1-D quadratic fit says the cost keeps falling (Gauss-Newton undershoots on soft modes), and
near the optimum the exact Hessian replaces ``J^T J`` when ``S`` is given (Newton steps,
quadratic convergence even with noisy residuals). Steps whose predicted gain is below
round-off are taken on the model's word, so noise-free problems converge to full precision.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from ..errors import AT_LEAST_1, NON_NEGATIVE, ConfigError, Limit, check_limits, check_shape, parse_choice
from ..geometry import se3_exp
from .blocksparse import BlockCholeskySymbolic, BlockSparseMatrix, Schedule, SolverMethod, analyze, solve_block_sparse

__all__ = ["LMConfig", "LMResult", "levenberg_marquardt_se3"]


def _unpack(out: tuple) -> tuple:
    return (out[0], out[1], out[2], out[3] if len(out) > 3 else None)


def _value(x):
    return x() if callable(x) else x


@dataclass(frozen=True)
class LMConfig:
    """Levenberg-Marquardt settings.

    Attributes:
        iterations: maximum number of iterations (accepted or rejected steps).
        tol: stop when a step lowers (or the quadratic model predicts it to lower) the cost by at
            most ``tol * cost``.
        step_tol: stop when an accepted step moves no pose by more than this (metres/radians).
            A negative ``tol`` or ``step_tol`` turns that test off (all ``iterations`` run).
        damping: initial Marquardt factor ``lambda`` (``H + lambda diag(H)``); 0 starts as pure
            Gauss-Newton.
        damping_up: factor applied to ``lambda`` after a rejected step (at least ``1e-6``).
        damping_down: factor applied after an accepted step.
        damping_max: a problem whose ``lambda`` exceeds this stops, not converged.
        solver: linear solver (:class:`SolverMethod` or its name).
        leaf_size: supernode size of the sparse Cholesky analysis, in poses.
        ordering: fill-reducing order of the sparse Cholesky, ``"band"`` or ``"nested"`` (see
            :func:`~torchslam.optim.blocksparse.analyze`).
        schedule: how the sparse Cholesky walks its elimination tree, ``"front"`` (one supernode
            at a time; fastest on the CPU) or ``"level"`` (batched over each level; fewer calls
            on accelerators, with ``ordering="nested"``), :class:`~torchslam.optim.Schedule`.
        line_search: after an accepted step, also try the minimiser of the 1-D quadratic
            through the cost, its exact slope and the step's cost (only step lengths > 1, up to
            ``max_step_scale``); speeds up the slow linear phase on soft modes of large graphs.
        max_step_scale: largest step length the line search tries.
        newton: when ``linearize`` also returns residual-curvature blocks ``S``, use the exact
            Hessian ``H + S`` once a problem is near its optimum; Gauss-Newton converges only
            linearly there when residuals are not small. A factorisation that is not positive
            definite falls back to ``H`` in the same iteration.
        newton_switch: a problem switches to the exact Hessian after an accepted step that
            lowered its cost by less than this fraction.
    """

    iterations: int = 20
    tol: float = 1e-8
    step_tol: float = 1e-10
    damping: float = 1e-6
    damping_up: float = 10.0
    damping_down: float = 0.1
    damping_max: float = 1e8
    solver: SolverMethod | str = SolverMethod.AUTO
    leaf_size: int = 16
    ordering: str = "band"
    schedule: Schedule | str = Schedule.FRONT
    line_search: bool = True
    max_step_scale: float = 8.0
    newton: bool = True
    newton_switch: float = 0.5

    LIMITS: ClassVar[dict[str, Limit]] = {
        "iterations": NON_NEGATIVE, "tol": Limit(), "step_tol": Limit(), "damping": NON_NEGATIVE,
        "damping_up": Limit(gt=1), "damping_down": Limit(gt=0, lt=1), "damping_max": Limit(gt=0, allow_inf=True),
        "leaf_size": AT_LEAST_1, "max_step_scale": Limit(ge=1), "newton_switch": Limit(ge=0, le=1),
    }

    def __post_init__(self) -> None:
        check_limits(self)
        if self.damping < 0 or self.damping_up <= 1 or not 0 < self.damping_down < 1:
            raise ConfigError(
                f"damping: expected damping >= 0, damping_up > 1, 0 < damping_down < 1, got "
                f"{self.damping}, {self.damping_up}, {self.damping_down}"
            )
        object.__setattr__(self, "solver", SolverMethod.parse(self.solver))
        object.__setattr__(self, "schedule", parse_choice(Schedule, self.schedule, "schedule"))


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt_se3`.

    Attributes:
        T: (N, 4, 4) optimised poses.
        cost: (B, iterations + 1) cost of each problem before the first and after every
            iteration (flat once a problem has stopped).
        iterations: (B,) int64 iterations each problem ran.
        converged: (B,) bool, True where the tolerance test was met.
        time_s: wall time of the call, seconds.
    """

    T: Tensor
    cost: Tensor
    iterations: Tensor
    converged: Tensor
    time_s: float


def levenberg_marquardt_se3(
    T: Tensor,
    node_problem: Tensor,
    num_problems: int,
    linearize: Callable[[Tensor], tuple[BlockSparseMatrix, Tensor, Tensor]],
    evaluate: Callable[[Tensor], Tensor],
    fixed: Tensor,
    config: LMConfig = LMConfig(),
    symbolic: BlockCholeskySymbolic | None = None,
) -> LMResult:
    """Minimise B independent least-squares problems over SE(3) poses.

    Args:
        T: (N, 4, 4) initial poses of all problems, concatenated.
        node_problem: (N,) int64 problem index of each pose, in ``[0, B)``.
        num_problems: B.
        linearize: ``T -> (H, g, cost)`` or ``(H, g, cost, S)`` with ``H`` a
            :class:`BlockSparseMatrix` over the N poses (same pattern every call), ``g`` (N, 6),
            ``cost`` (B,) (or a function returning it: only the first call's cost is read,
            later costs come from ``evaluate``) and optional ``S`` (N, 6, 6) residual-curvature diagonal blocks (the
            exact Hessian is ``H + S``), or a function returning them, called only when a
            Newton step is tried.
        evaluate: ``T -> cost`` (B,), the same cost without the linearisation.
        fixed: (N,) bool mask of poses held constant (gauges).
        config: iteration and damping settings.
        symbolic: optional sparse analysis of ``H``'s pattern with ``fixed`` (reused if given).

    Returns:
        The optimised poses and per-problem history. A step that makes the cost non-finite or
        whose factorisation fails is rejected, so poses never become NaN.
    """
    start = time.perf_counter()
    dims: dict[str, int] = {}
    check_shape(T, "N 4 4", "T", dims)
    check_shape(node_problem, "N", "node_problem", dims)
    check_shape(fixed, "N", "fixed", dims)
    B = num_problems
    dev, dt = T.device, T.dtype
    H, g, cost, S = _unpack(linearize(T))
    cost = _value(cost)
    if symbolic is None and config.solver in (SolverMethod.AUTO, SolverMethod.CHOLESKY):
        symbolic = analyze(H.num_nodes, H.rows, H.cols, fixed, H.block_size, config.leaf_size, config.ordering)
    lam = torch.full((B,), config.damping, dtype=dt, device=dev)
    active = torch.ones(B, dtype=torch.bool, device=dev)
    converged = torch.zeros(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.int64, device=dev)
    history = [cost.detach()]
    newton_ready = torch.zeros(B, dtype=torch.bool, device=dev)
    newton = config.newton and S is not None
    # Host copies of the decisions the loop branches on, refreshed by one transfer at the end
    # of every iteration (a second one only in iterations that try the exact Hessian).
    any_active, any_newton = B > 0, False
    for _ in range(config.iterations):
        if not any_active:
            break
        d = torch.diagonal(H.diag, dim1=-2, dim2=-1)
        # Marquardt scaling with a small per-pose floor so that a zero diagonal entry still
        # receives some damping.
        damp = lam[node_problem][:, None] * (d + 1e-9 * d.mean(-1, keepdim=True))
        rhs = -g * active[node_problem][:, None].to(dt)
        use_newton = newton_ready & active if newton else torch.zeros_like(active)
        try_newton = newton and any_newton
        for attempt in range(2):
            if try_newton:
                if callable(S):
                    S = S()
                model = BlockSparseMatrix(H.diag + S * use_newton[node_problem][:, None, None].to(dt), H.off, H.rows, H.cols)
            else:
                model = H
            delta, ok = solve_block_sparse(
                model.add_to_diagonal(damp), rhs, fixed, config.solver, symbolic, schedule=config.schedule
            )
            bad_node = (~ok | ~torch.isfinite(delta).all(-1)).to(dt)
            ok_problem = torch.zeros(B, dtype=dt, device=dev).index_add(0, node_problem, bad_node) == 0
            if attempt == 1 or not try_newton:
                break
            failed = use_newton & ~ok_problem
            # The exact Hessian is indefinite here: Gauss-Newton for those problems this time.
            use_newton = use_newton & ~failed
            any_failed, try_newton = torch.stack([failed.any(), use_newton.any()]).tolist()
            if not any_failed:
                break
            newton_ready = newton_ready & ~failed
        T_new = se3_exp(delta) @ T
        cost_new = evaluate(T_new)
        step = delta.detach().abs().amax(-1)
        step_p = torch.zeros(B, dtype=dt, device=dev).scatter_reduce(0, node_problem, step, "amax")
        decrease = (cost - cost_new).detach()
        # Reduction predicted by the undamped quadratic model of the cost r^T r, whose gradient
        # is 2 g and Hessian 2 H: -2 g.d - d.H d. When it is below the tolerance there is
        # nothing left to gain, whatever round-off does to the evaluated cost (noise-free
        # problems sit at a round-off floor). As (H + D) d = -g, d.H d = -g.d - d.D d, so no
        # product with H is needed.
        dd = delta.detach()
        pred_node = -(g.detach() * dd).sum(-1) + (damp.detach() * dd * dd).sum(-1)
        pred = torch.zeros(B, dtype=dt, device=dev).index_add(0, node_problem, pred_node)
        limit = config.tol * cost.detach()
        # Close to the optimum the evaluated cost cannot resolve the step any more (its
        # round-off exceeds the predicted gain), so a step whose predicted gain is below
        # 1e-10 of the cost is taken on the model's word, as plain Gauss-Newton would.
        near = ok_problem & (pred <= 1e-10 * cost.detach())
        accept = active & ok_problem & torch.isfinite(cost_new) & ((cost_new <= cost) | near)
        # A Newton step (exact Hessian, negligible damping) whose gain the quadratic model
        # predicted to within the tolerance has landed at the optimum up to higher-order terms
        # (the new gradient is O(|d|^2)): no confirmation step is needed.
        newton_exact = use_newton & (lam <= 1e-4) & accept & ((decrease - pred).abs() <= limit)
        done = active & (
            (accept & (decrease <= limit)) | (ok_problem & (pred <= limit)) | (step_p <= config.step_tol) | newton_exact
        )
        if config.line_search:
            # Floppy modes of large pose graphs are softer than the Gauss-Newton model says
            # (residual curvature), so the step undershoots. Fit c(a) = c0 + a s + a^2 k / 2
            # through the exact slope s = 2 g.d and c(1), and try the minimiser a* > 1. The
            # extended poses are evaluated whether or not a problem extends: one cost
            # evaluation is cheaper than a synchronisation to decide.
            slope = torch.zeros(B, dtype=dt, device=dev).index_add(0, node_problem, 2 * (g * delta).sum(-1))
            kappa = 2 * (cost_new - cost - slope)
            a_star = torch.where(kappa > 0, -slope / torch.where(kappa > 0, kappa, torch.ones_like(kappa)), torch.ones_like(kappa))
            a_star = a_star.clamp(1.0, config.max_step_scale)
            extend = accept & (a_star.detach() > 1.2)
            T_ext = se3_exp(a_star[node_problem][:, None] * delta) @ T
            cost_ext = evaluate(T_ext)
            better = extend & torch.isfinite(cost_ext) & (cost_ext < cost_new)
            T_new = torch.where(better[node_problem][:, None, None], T_ext, T_new)
            cost_new = torch.where(better, cost_ext, cost_new)
        T = torch.where(accept[node_problem][:, None, None], T_new, T)
        rel = (cost.detach() - cost_new.detach()) / cost.detach().clamp_min(torch.finfo(dt).tiny)
        newton_ready = torch.where(accept, rel < config.newton_switch, newton_ready)
        cost = torch.where(accept, cost_new, cost)
        lam = torch.where(accept, lam * config.damping_down, (lam * config.damping_up).clamp_min(1e-6))
        iters = iters + active.to(torch.int64)
        converged = converged | done
        active = active & ~done & (lam <= config.damping_max)
        history.append(cost.detach())
        any_active, relinearize, any_newton = torch.stack(
            [active.any(), (accept & active).any(), (newton_ready & active).any()]
        ).tolist()
        if relinearize:
            H, g, _, S = _unpack(linearize(T))
    cost_hist = torch.stack(history, dim=1)
    return LMResult(T, cost_hist, iters, converged, time.perf_counter() - start)
