"""SE(3) pose graph: keyframe poses linked by measured relative transforms (NI-SLAM §9.2).

Edge ``e`` measures ``T_ij = T_wi^-1 T_wj`` (pose of node j in node i's frame). Its residual is

    r_e = log(T_ij_meas^-1 T_wi^-1 T_wj)            (6-vector, translation first)

and the cost ``sum_e r_e^T Omega_e r_e`` with 6x6 information matrices ``Omega_e``. Poses are
updated on the left, ``T <- exp(delta) T``. With ``E = T_ij_meas^-1 T_wi^-1 T_wj``, a left
perturbation of ``T_wj`` gives ``E exp(Ad(T_wj^-1) delta_j)`` and one of ``T_wi`` gives
``E exp(-Ad(T_wj^-1) delta_i)``, so

    J_j = Jr^-1(r) Ad(T_wj^-1),    J_i = -J_j,

where ``Jr^-1(r) ~ I + ad(r) / 2`` is the inverse right Jacobian to first order (exact at the
optimum of a consistent graph, where ``r -> 0``). Everything is batched over edges and solved
with the shared block-sparse Levenberg-Marquardt of :mod:`torchslam.optim`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import DTypeError, InvalidValueError, check_float, check_shape
from ..geometry import se3_adjoint, se3_inverse, se3_log, skew
from ..optim import BlockSparseMatrix, LMConfig, levenberg_marquardt_se3

__all__ = [
    "EdgeTest", "PoseGraphResult", "chi2_quantile", "edge_consistency", "edge_residuals", "graph_cost",
    "linearize_pose_graph", "optimize_pose_graph",
]


@dataclass(frozen=True)
class PoseGraphResult:
    """Outcome of :func:`optimize_pose_graph`.

    Attributes:
        T_wc: (N, 4, 4) float64 optimised poses.
        cost: (iterations + 1,) cost before and after each iteration.
        iterations: iterations run.
        converged: whether the tolerance test was met.
        time_s: wall time, seconds.
    """

    T_wc: Tensor
    cost: Tensor
    iterations: int
    converged: bool
    time_s: float


def _check_edges(T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor, information: Tensor) -> None:
    dims: dict[str, int] = {}
    check_shape(T_wc, "N 4 4", "T_wc", dims)
    check_float(T_wc, "T_wc")
    check_shape(i, "E", "i", dims)
    check_shape(j, "E", "j", dims)
    check_shape(T_ij, "E 4 4", "T_ij", dims)
    check_shape(information, "E 6 6", "information", dims)
    n = dims["N"]
    for name, idx in (("i", i), ("j", j)):
        if idx.dtype != torch.int64:
            raise DTypeError(f"{name}: expected int64 node indices, got {idx.dtype}")
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n):
            raise InvalidValueError(f"{name}: node indices must lie in [0, {n}), got [{int(idx.min())}, {int(idx.max())}]")
    if bool((i == j).any()):
        raise InvalidValueError("i, j: an edge must join two different nodes")


def _ad(xi: Tensor) -> Tensor:
    """(..., 6) twist -> (..., 6, 6) ``ad(xi) = [[phi^, rho^], [0, phi^]]``."""
    rho, phi = skew(xi[..., :3]), skew(xi[..., 3:])
    top = torch.cat([phi, rho], dim=-1)
    bottom = torch.cat([torch.zeros_like(phi), phi], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def edge_residuals(T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor) -> Tensor:
    """Residuals ``log(T_ij^-1 T_wi^-1 T_wj)`` of all edges.

    Args:
        T_wc: (N, 4, 4) node poses.
        i, j: (E,) int64 node indices of each edge.
        T_ij: (E, 4, 4) measured relative transforms.

    Returns:
        (E, 6) residual twists, translation first.
    """
    return se3_log(se3_inverse(T_ij) @ se3_inverse(T_wc[i]) @ T_wc[j])


def linearize_pose_graph(
    T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor, information: Tensor
) -> tuple[BlockSparseMatrix, Tensor, Tensor]:
    """Normal equations of the pose graph at ``T_wc`` (all edges at once).

    Returns:
        H: block-sparse (N x N blocks of 6x6) Gauss-Newton matrix ``J^T Omega J``.
        g: (N, 6) gradient ``J^T Omega r``.
        cost: () ``sum r^T Omega r``.
    """
    r = edge_residuals(T_wc, i, j, T_ij)  # (E, 6)
    Jj = (torch.eye(6, dtype=r.dtype, device=r.device) + 0.5 * _ad(r)) @ se3_adjoint(se3_inverse(T_wc[j]))
    Ji = -Jj
    Om = information.to(r.dtype)
    OJi, OJj = Om @ Ji, Om @ Jj
    N = T_wc.shape[0]
    diag = T_wc.new_zeros(N, 6, 6)
    diag.index_add_(0, i, Ji.transpose(-1, -2) @ OJi)
    diag.index_add_(0, j, Jj.transpose(-1, -2) @ OJj)
    off = Ji.transpose(-1, -2) @ OJj  # block (i, j)
    Omr = (Om @ r[..., None])[..., 0]
    g = T_wc.new_zeros(N, 6)
    g.index_add_(0, i, (Ji.transpose(-1, -2) @ Omr[..., None])[..., 0])
    g.index_add_(0, j, (Jj.transpose(-1, -2) @ Omr[..., None])[..., 0])
    cost = (r * Omr).sum()
    return BlockSparseMatrix(diag, off, i, j), g, cost


def optimize_pose_graph(
    T_wc: Tensor,
    i: Tensor,
    j: Tensor,
    T_ij: Tensor,
    information: Tensor,
    fixed: int | Tensor = 0,
    config: LMConfig = LMConfig(iterations=30, tol=1e-12),
) -> PoseGraphResult:
    """Optimise keyframe poses against relative-pose measurements with Levenberg-Marquardt.

    Args:
        T_wc: (N, 4, 4) initial camera-to-world poses (float64 recommended).
        i, j: (E,) int64 node indices; edge e measures node j in node i's frame.
        T_ij: (E, 4, 4) measured ``T_wi^-1 T_wj``.
        information: (E, 6, 6) symmetric positive semi-definite information matrices
            (inverse covariances of the residual twist, translation first).
        fixed: index (or (N,) bool mask) of the nodes held constant (the gauge).
        config: iteration and damping settings.

    Returns:
        PoseGraphResult with the optimised poses; a failed step is rejected, never NaN.
    """
    _check_edges(T_wc, i, j, T_ij, information)
    N = T_wc.shape[0]
    if isinstance(fixed, int):
        mask = torch.zeros(N, dtype=torch.bool, device=T_wc.device)
        mask[fixed] = True
    else:
        mask = fixed.to(torch.bool)
    T_ij = T_ij.to(T_wc.dtype)
    information = information.to(T_wc.dtype)

    def linearize(T: Tensor):
        H, g, cost = linearize_pose_graph(T, i, j, T_ij, information)
        return H, g, cost.reshape(1)

    def evaluate(T: Tensor) -> Tensor:
        return _cost(T, i, j, T_ij, information).reshape(1)

    node_problem = torch.zeros(N, dtype=torch.int64, device=T_wc.device)
    res = levenberg_marquardt_se3(T_wc, node_problem, 1, linearize, evaluate, mask, config)
    return PoseGraphResult(res.T, res.cost[0], int(res.iterations[0]), bool(res.converged[0]), res.time_s)


def graph_cost(T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor, information: Tensor) -> Tensor:
    """The pose graph's cost ``chi^2 = sum_e r_e^T Omega_e r_e`` at ``T_wc``.

    Args:
        T_wc: (N, 4, 4) node poses.
        i, j: (E,) int64 node indices of each edge.
        T_ij: (E, 4, 4) measured relative transforms.
        information: (E, 6, 6) information matrices.

    Returns:
        () chi^2 in ``T_wc``'s dtype (0 for no edges).
    """
    _check_edges(T_wc, i, j, T_ij, information)
    if not i.numel():
        return T_wc.new_zeros(())
    return _cost(T_wc, i, j, T_ij.to(T_wc.dtype), information.to(T_wc.dtype))


def _cost(T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor, information: Tensor) -> Tensor:
    """() ``sum_e r_e^T Omega_e r_e``, inputs already checked and in one dtype."""
    r = edge_residuals(T_wc, i, j, T_ij)
    return (r * (information @ r[..., None])[..., 0]).sum()


@dataclass(frozen=True)
class EdgeTest:
    """Outcome of :func:`edge_consistency`.

    Attributes:
        chi2_increase: () ``chi^2`` of the optimised graph with the new edge minus that of the
            optimised graph without it.
        dof: degrees of freedom of the new edge (rank of its information matrix).
        threshold: the ``chi^2`` quantile the increase is compared with.
        consistent: ``chi2_increase <= threshold`` and the optimisation stayed finite.
        result: the optimisation of the graph with the new edge.
    """

    chi2_increase: Tensor
    dof: int
    threshold: float
    consistent: bool
    result: PoseGraphResult


def edge_consistency(
    T_wc: Tensor,
    i: Tensor,
    j: Tensor,
    T_ij: Tensor,
    information: Tensor,
    new_i: int,
    new_j: int,
    new_T_ij: Tensor,
    new_information: Tensor,
    quantile: float,
    fixed: int | Tensor = 0,
    config: LMConfig = LMConfig(iterations=20, tol=1e-10),
) -> EdgeTest:
    """Test a new edge (a loop closure) for consistency with the graph: the chi-square increase.

    The graph is first optimised without the new edge from ``T_wc`` (a chain of odometry edges
    composed is at its optimum already: one linearisation), then with it from there. For a
    linear-Gaussian graph the increase of the optimised cost when the edge is added equals the Mahalanobis norm of the edge's innovation
    ``nu = log(T_ij_new^-1 T_wi^-1 T_wj)`` against its predicted covariance
    ``S = Omega_new^+ + J P J^T`` (``P`` the graph's pose covariance), and is chi-square
    distributed with the edge's degrees of freedom when the edge and the graph agree; a wrong
    edge raises it by its squared error in units of that covariance.

    Args:
        T_wc: (N, 4, 4) initial poses (float64 recommended).
        i, j, T_ij, information: the graph's edges, as for :func:`optimize_pose_graph`.
        new_i, new_j: nodes of the new edge.
        new_T_ij: (4, 4) its measured ``T_wi^-1 T_wj``.
        new_information: (6, 6) its information matrix (may be rank-deficient: a translation-only
            edge has rank 3).
        quantile: probability of the chi-square quantile in (0, 1): the edge is consistent when its
            increase is at most the ``quantile`` quantile with its degrees of freedom.
        fixed: the gauge, as for :func:`optimize_pose_graph`.
        config: the optimisation's settings.

    Returns:
        EdgeTest.

    Raises:
        InvalidValueError: ``quantile`` outside (0, 1) or a new edge without information.
    """
    if not 0.0 < quantile < 1.0:
        raise InvalidValueError(f"quantile: expected a probability in (0, 1), got {quantile}")
    check_shape(new_T_ij, "4 4", "new_T_ij")
    check_shape(new_information, "6 6", "new_information")
    dof = int(torch.linalg.matrix_rank(new_information.to(torch.float64)))
    if dof == 0:
        raise InvalidValueError("new_information: the new edge carries no information (rank 0)")
    dt, dev = T_wc.dtype, T_wc.device
    if i.numel():
        T_wc = optimize_pose_graph(T_wc, i, j, T_ij, information, fixed=fixed, config=config).T_wc
    before = graph_cost(T_wc, i, j, T_ij, information)
    i2 = torch.cat([i, torch.tensor([new_i], dtype=torch.int64, device=dev)])
    j2 = torch.cat([j, torch.tensor([new_j], dtype=torch.int64, device=dev)])
    T2 = torch.cat([T_ij.to(dt), new_T_ij.to(dt)[None]])
    info2 = torch.cat([information.to(dt), new_information.to(dt)[None]])
    res = optimize_pose_graph(T_wc, i2, j2, T2, info2, fixed=fixed, config=config)
    after = graph_cost(res.T_wc, i2, j2, T2, info2)
    increase = after - before
    threshold = chi2_quantile(quantile, dof)
    finite = bool(torch.isfinite(res.T_wc).all()) and bool(torch.isfinite(increase))
    return EdgeTest(increase, dof, threshold, finite and float(increase) <= threshold, res)


@functools.lru_cache(maxsize=64)
def chi2_quantile(probability: float, dof: int) -> float:
    """The ``probability`` quantile of the chi-square distribution with ``dof`` degrees of freedom.

    Newton's method on the regularised incomplete gamma function (``torch.special``, float64)
    from the Wilson-Hilferty approximation, on the upper tail above the median so that a
    quantile near 1 keeps its precision: agrees with SciPy's ``chi2.ppf`` to 1e-14 relative up to
    12 degrees of freedom and 1e-9 at 50, where torch's incomplete gamma is less precise
    (``tests/backend/test_posegraph.py``). SciPy's statistics module is not used: its
    import took 0.4-0.9 s, paid in the tracking thread at a run's first loop test.

    Raises:
        InvalidValueError: ``probability`` outside (0, 1) or ``dof`` not positive.
    """
    if not 0.0 < probability < 1.0:
        raise InvalidValueError(f"probability: must be in (0, 1), got {probability}")
    if not dof > 0:
        raise InvalidValueError(f"dof: must be > 0, got {dof}")
    k = 0.5 * dof
    log_norm = k * math.log(2.0) + math.lgamma(k)
    upper = probability > 0.5
    target = 1.0 - probability if upper else probability
    z = float(torch.special.ndtri(torch.tensor(probability, dtype=torch.float64)))
    c = 2.0 / (9.0 * dof)
    x = dof * max(1.0 - c + z * math.sqrt(c), 0.1) ** 3
    for _ in range(100):
        t = torch.tensor([k], dtype=torch.float64), torch.tensor([0.5 * x], dtype=torch.float64)
        tail = float(torch.special.gammaincc(*t) if upper else torch.special.gammainc(*t))
        density = math.exp((k - 1.0) * math.log(x) - 0.5 * x - log_norm)
        if density == 0.0:
            break
        step = (tail - target) / density * (1.0 if upper else -1.0)
        x_new = x + step if x + step > 0 else 0.5 * x  # stay on the positive axis
        if abs(x_new - x) <= 1e-14 * x:
            x = x_new
            break
        x = x_new
    return x
