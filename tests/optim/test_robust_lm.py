"""Robust IRLS weights against the derivative of their losses; the batched LM driver."""

from __future__ import annotations

import pytest
import torch

from torchslam.errors import ConfigError
from torchslam.geometry import se3_exp, se3_inverse, se3_log
from torchslam.optim import BlockSparseMatrix, LMConfig, RobustKernel, levenberg_marquardt_se3, robust_cost, robust_weight


@pytest.mark.parametrize("kernel", list(RobustKernel))
def test_weight_is_derivative_over_residual(kernel):
    r = torch.linspace(0.01, 3.0, 57, dtype=torch.float64).requires_grad_(True)
    scale = 0.7
    (d,) = torch.autograd.grad(robust_cost(r, kernel, scale).sum(), r)
    w = robust_weight(r.detach(), kernel, scale)
    assert torch.allclose(w, d / r.detach(), atol=1e-12)
    assert torch.all((w >= 0) & (w <= 1))


def test_weights_finite_gradient_at_zero_and_parse_errors():
    r = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    for k in [k for k in RobustKernel if k is not RobustKernel.L2]:
        (gr,) = torch.autograd.grad(robust_weight(r, k, 0.1).sum(), r)
        assert torch.isfinite(gr).all()
    assert RobustKernel.parse("Cauchy") is RobustKernel.CAUCHY
    assert RobustKernel.parse(None) is RobustKernel.L2
    with pytest.raises(ConfigError, match=r"robust kernel: 'bisquare' is not one of \['l2', 'huber'"):
        RobustKernel.parse("bisquare")
    with pytest.raises(ConfigError, match="scale"):
        robust_weight(r, "huber", 0.0)
    with pytest.raises(ConfigError, match="damping"):
        LMConfig(damping_up=0.5)


def _prior_problem(targets: torch.Tensor):
    """Poses pulled towards targets through point residuals: r = T p - T_target p, p unit axes."""
    pts = torch.cat([torch.zeros(1, 3), torch.eye(3)]).to(torch.float64)  # (4, 3)

    def residuals(T):
        q = (T[:, None, :3, :3] @ pts[..., None])[..., 0] + T[:, None, :3, 3]
        qt = (targets[:, None, :3, :3] @ pts[..., None])[..., 0] + targets[:, None, :3, 3]
        return q, q - qt

    def linearize(T):
        q, r = residuals(T)
        eye = torch.eye(3, dtype=T.dtype).expand(q.shape[:-1] + (3, 3))
        qx = torch.zeros(q.shape[:-1] + (3, 3), dtype=T.dtype)
        qx[..., 0, 1], qx[..., 0, 2], qx[..., 1, 2] = -q[..., 2], q[..., 1], -q[..., 0]
        qx = qx - qx.transpose(-1, -2)
        J = torch.cat([eye, -qx], -1)  # (N, 4, 3, 6)
        H = (J.transpose(-1, -2) @ J).sum(1)
        g = (J.transpose(-1, -2) @ r[..., None])[..., 0].sum(1)
        cost = (r * r).sum((-1, -2))
        empty = torch.zeros(0, dtype=torch.int64)
        return BlockSparseMatrix(H, H.new_zeros(0, 6, 6), empty, empty), g, cost

    return linearize, lambda T: linearize(T)[2]


def test_lm_recovers_targets_per_problem():
    g = torch.Generator().manual_seed(0)
    targets = se3_exp(torch.randn(5, 6, generator=g, dtype=torch.float64))
    T0 = se3_exp(0.3 * torch.randn(5, 6, generator=g, dtype=torch.float64)) @ targets
    lin, ev = _prior_problem(targets)
    fixed = torch.zeros(5, dtype=torch.bool)
    res = levenberg_marquardt_se3(T0, torch.arange(5), 5, lin, ev, fixed, LMConfig(iterations=30))
    assert res.converged.all()
    assert se3_log(se3_inverse(res.T) @ targets).abs().max() < 1e-9
    assert res.cost.shape[0] == 5 and torch.all(res.cost[:, -1] < 1e-18)
    # A problem that starts at its optimum stops at once; the others iterate on.
    T0[2] = targets[2]
    res2 = levenberg_marquardt_se3(T0, torch.arange(5), 5, lin, ev, fixed, LMConfig(iterations=30))
    assert int(res2.iterations[2]) == 1 and int(res2.iterations.max()) > 2
    # Fixed poses do not move.
    fixed[1] = True
    res3 = levenberg_marquardt_se3(T0, torch.arange(5), 5, lin, ev, fixed, LMConfig(iterations=30))
    assert torch.equal(res3.T[1], T0[1])


def test_indefinite_exact_hessian_falls_back_to_gauss_newton():
    g = torch.Generator().manual_seed(1)
    targets = se3_exp(torch.randn(3, 6, generator=g, dtype=torch.float64))
    T0 = se3_exp(0.2 * torch.randn(3, 6, generator=g, dtype=torch.float64)) @ targets
    lin, ev = _prior_problem(targets)

    def lin_bad(T):  # a curvature term that makes H + S indefinite everywhere
        H, gr, c = lin(T)
        return H, gr, c, -10 * H.diag

    res = levenberg_marquardt_se3(T0, torch.arange(3), 3, lin_bad, ev, torch.zeros(3, dtype=torch.bool), LMConfig(iterations=30))
    assert res.converged.all() and torch.isfinite(res.T).all()
    assert se3_log(se3_inverse(res.T) @ targets).abs().max() < 1e-9


def test_lm_lazy_cost_matches_eager_and_is_read_once():
    g = torch.Generator().manual_seed(3)
    targets = se3_exp(torch.randn(4, 6, generator=g, dtype=torch.float64))
    T0 = se3_exp(0.3 * torch.randn(4, 6, generator=g, dtype=torch.float64)) @ targets
    lin, ev = _prior_problem(targets)
    calls = []

    def lazy(T):
        H, gr, cost = lin(T)

        def c():
            calls.append(1)
            return cost

        return H, gr, c

    fixed = torch.zeros(4, dtype=torch.bool)
    eager = levenberg_marquardt_se3(T0, torch.arange(4), 4, lin, ev, fixed, LMConfig(iterations=30))
    res = levenberg_marquardt_se3(T0, torch.arange(4), 4, lazy, ev, fixed, LMConfig(iterations=30))
    assert len(calls) == 1  # only the start point's cost is read
    assert torch.equal(res.T, eager.T) and torch.equal(res.cost, eager.cost)
    assert torch.equal(res.iterations, eager.iterations)
