import pytest
import torch

from torchslam.backend import edge_residuals, linearize_pose_graph, optimize_pose_graph
from torchslam.errors import InvalidValueError, ShapeError
from torchslam.geometry import se3_exp, se3_inverse, se3_log

from tests._helpers import seeded


def _loop_graph(n=30, seed=0, noise=0.0):
    """Poses on a circle, odometry edges between neighbours and loop edges back to the start."""
    g = seeded(seed)
    angles = torch.linspace(0, 2 * torch.pi * (n - 1) / n, n, dtype=torch.float64)
    xi = torch.zeros(n, 6, dtype=torch.float64)
    xi[:, 0], xi[:, 2], xi[:, 4] = 2 * torch.cos(angles), 2 * torch.sin(angles), -angles
    xi[:, 3:] += 0.05 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    T_gt = se3_exp(xi)
    i = torch.cat([torch.arange(n - 1), torch.tensor([n - 1, n - 2, 0])])
    j = torch.cat([torch.arange(1, n), torch.tensor([0, 0, 5])])
    T_ij = se3_inverse(T_gt[i]) @ T_gt[j]
    if noise:
        T_ij = se3_exp(noise * torch.randn(len(i), 6, generator=g, dtype=torch.float64)) @ T_ij
    info = torch.eye(6, dtype=torch.float64).expand(len(i), 6, 6).clone()
    return T_gt, i, j, T_ij, info


def test_gradient_and_hessian_match_autograd():
    # Jr^-1 is taken to first order, so the gradient is exact up to O(|r|^2): keep residuals ~1e-2.
    T_gt, i, j, T_ij, info = _loop_graph(8, noise=0.005)
    T0 = se3_exp(0.005 * torch.randn(8, 6, generator=seeded(1), dtype=torch.float64)) @ T_gt
    info = info * torch.linspace(0.5, 2.0, 6, dtype=torch.float64)  # anisotropic
    H, g, cost = linearize_pose_graph(T0, i, j, T_ij, info)

    def f(delta):
        r = edge_residuals(se3_exp(delta.reshape(8, 6)) @ T0, i, j, T_ij)
        return (r * (info @ r[..., None])[..., 0]).sum()

    d0 = torch.zeros(48, dtype=torch.float64)
    g_ref = torch.autograd.functional.jacobian(f, d0).reshape(8, 6)
    torch.testing.assert_close(2 * g, g_ref, atol=2e-4 * g_ref.abs().max().item(), rtol=0)
    assert cost.item() == pytest.approx(f(d0).item(), rel=1e-12)
    # Gauss-Newton matrix against J^T Omega J from autograd on the residual vector.
    def res(delta):
        return edge_residuals(se3_exp(delta.reshape(8, 6)) @ T0, i, j, T_ij)

    J = torch.autograd.functional.jacobian(res, d0).reshape(len(i), 6, 48)
    H_ref = torch.einsum("eak,eab,ebl->kl", J, info, J)
    H_dense = torch.zeros(48, 48, dtype=torch.float64)
    for n in range(8):
        H_dense[6 * n : 6 * n + 6, 6 * n : 6 * n + 6] = H.diag[n]
    for e in range(len(i)):
        a, b = int(H.rows[e]), int(H.cols[e])
        H_dense[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] += H.off[e]
        H_dense[6 * b : 6 * b + 6, 6 * a : 6 * a + 6] += H.off[e].T
    torch.testing.assert_close(H_dense, H_ref, atol=1e-3, rtol=0)


def test_planted_loop_returns_to_ground_truth():
    T_gt, i, j, T_ij, info = _loop_graph(30)
    # Drifted initial guess: compose noisy odometry along the chain.
    g = seeded(3)
    T0 = [T_gt[0]]
    for k in range(29):
        step = se3_exp(0.02 * torch.randn(6, generator=g, dtype=torch.float64)) @ (se3_inverse(T_gt[k]) @ T_gt[k + 1])
        T0.append(T0[-1] @ step)
    T0 = torch.stack(T0)
    assert se3_log(se3_inverse(T0) @ T_gt).norm(dim=-1).max() > 0.1
    res = optimize_pose_graph(T0, i, j, T_ij, info)
    assert res.converged and res.cost[-1] < 1e-16
    assert se3_log(se3_inverse(res.T_wc) @ T_gt).norm(dim=-1).max() < 1e-7
    torch.testing.assert_close(res.T_wc[0], T_gt[0], atol=0, rtol=0)  # gauge held


def test_noisy_measurements_reduce_cost_and_stay_finite():
    T_gt, i, j, T_ij, info = _loop_graph(20, noise=0.01)
    res = optimize_pose_graph(T_gt.clone(), i, j, T_ij, info)
    assert res.cost[-1] < res.cost[0] and torch.isfinite(res.T_wc).all()


def test_bad_edges_raise():
    T_gt, i, j, T_ij, info = _loop_graph(8)
    with pytest.raises(InvalidValueError, match="node indices must lie in"):
        optimize_pose_graph(T_gt, i + 10, j, T_ij, info)
    with pytest.raises(InvalidValueError, match="two different nodes"):
        optimize_pose_graph(T_gt, i, i, T_ij, info)
    with pytest.raises(ShapeError, match="information"):
        optimize_pose_graph(T_gt, i, j, T_ij, info[:, :3])
