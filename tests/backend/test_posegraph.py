import pytest
import torch

from torchslam.backend import chi2_quantile, edge_consistency, edge_residuals, graph_cost, linearize_pose_graph, optimize_pose_graph
from torchslam.errors import InvalidValueError, ShapeError
from torchslam.optim import LMConfig
from torchslam.geometry import se3_exp, se3_inverse, se3_log

from tests._helpers import seeded
from tests._references import reference_edge_innovation


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


def _drifting_chain(n=10, seed=0, sigma_t=0.01, sigma_r=0.002):
    """A chain of odometry edges measured with noise of the stated sigmas, composed (its optimum)."""
    g = seeded(seed)
    xi = torch.zeros(n, 6, dtype=torch.float64)
    xi[:, 0] = torch.linspace(0, 2.0, n, dtype=torch.float64)
    xi[:, 1] = 0.3 * torch.sin(torch.linspace(0, 3, n, dtype=torch.float64))
    xi[:, 3:] = 0.1 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    T_gt = se3_exp(xi)
    i, j = torch.arange(n - 1), torch.arange(1, n)
    noise = torch.cat([sigma_t * torch.randn(n - 1, 3, generator=g, dtype=torch.float64),
                       sigma_r * torch.randn(n - 1, 3, generator=g, dtype=torch.float64)], -1)
    T_ij = (se3_inverse(T_gt[i]) @ T_gt[j]) @ se3_exp(noise)
    info = torch.diag(torch.tensor([sigma_t**-2] * 3 + [sigma_r**-2] * 3, dtype=torch.float64)).expand(n - 1, 6, 6).clone()
    T_est = [T_gt[0]]
    for e in range(n - 1):
        T_est.append(T_est[-1] @ T_ij[e])
    return T_gt, torch.stack(T_est), i, j, T_ij, info


@pytest.mark.parametrize("translation_only", [True, False])
def test_chi2_increase_equals_the_innovation_test(translation_only):
    # Small noise: the SE(3) graph is nearly linear, so the optimised cost increase must equal the
    # dense linear-Gaussian innovation norm nu^T S^-1 nu.
    T_gt, T0, i, j, T_ij, info = _drifting_chain(8, sigma_t=0.002, sigma_r=0.0005)
    n = T0.shape[0]
    diag = torch.tensor([0.002**-2] * 3 + ([0.0] * 3 if translation_only else [0.0005**-2] * 3), dtype=torch.float64)
    T_loop = se3_inverse(T_gt[0]) @ T_gt[n - 1] @ se3_exp(torch.tensor([0.003, -0.002, 0.001, 0.0, 0.0, 0.0], dtype=torch.float64))
    test = edge_consistency(T0, i, j, T_ij, info, 0, n - 1, T_loop, torch.diag(diag), 0.99,
                            config=LMConfig(iterations=30, tol=1e-14))
    ref = reference_edge_innovation(T0, i, j, T_ij, info, 0, n - 1, T_loop, torch.diag(diag))
    assert test.dof == (3 if translation_only else 6)
    assert test.threshold == pytest.approx(chi2_quantile(0.99, test.dof))
    assert ref > 1.0  # a visible increase, not a trivial zero
    assert float(test.chi2_increase) == pytest.approx(ref, rel=2e-3)


def test_true_loop_accepted_false_loops_rejected():
    # Large drift (6 mm per edge over 30 edges) that honest covariances explain: the true loop is
    # consistent even though it moves the chain's end by centimetres, a 0.3 m wrong one is not.
    T_gt, T0, i, j, T_ij, info = _drifting_chain(31, seed=3, sigma_t=0.006, sigma_r=0.001)
    n = T0.shape[0]
    drift = float((T0[-1, :3, 3] - T_gt[-1, :3, 3]).norm())
    assert drift > 0.03
    info_loop = torch.diag(torch.tensor([1e-3**-2] * 3 + [0.0] * 3, dtype=torch.float64))
    T_true = se3_inverse(T_gt[0]) @ T_gt[-1]
    ok = edge_consistency(T0, i, j, T_ij, info, 0, n - 1, T_true, info_loop, 0.999)
    assert ok.consistent, float(ok.chi2_increase)
    # The optimised poses move toward ground truth.
    assert float((ok.result.T_wc[-1, :3, 3] - T_gt[-1, :3, 3]).norm()) < 0.3 * drift
    T_wrong = T_true.clone()
    T_wrong[:3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)
    bad = edge_consistency(T0, i, j, T_ij, info, 0, n - 1, T_wrong, info_loop, 0.999)
    assert not bad.consistent and float(bad.chi2_increase) > 3 * bad.threshold
    # A different place: the true measurement attached to a node halfway along the chain.
    elsewhere = edge_consistency(T0, i, j, T_ij, info, n // 2, n - 1, T_true, info_loop, 0.999)
    assert not elsewhere.consistent


def test_graph_cost_and_edge_consistency_bad_input():
    T_gt, T0, i, j, T_ij, info = _drifting_chain(4)
    assert float(graph_cost(T0, i, j, T_ij, info)) == pytest.approx(0.0, abs=1e-18)
    assert float(graph_cost(T_gt, i, j, T_ij, info)) > 0
    eye = torch.eye(4, dtype=torch.float64)
    with pytest.raises(InvalidValueError, match="quantile"):
        edge_consistency(T0, i, j, T_ij, info, 0, 3, eye, info[0], 1.0)
    with pytest.raises(InvalidValueError, match="no information"):
        edge_consistency(T0, i, j, T_ij, info, 0, 3, eye, torch.zeros(6, 6, dtype=torch.float64), 0.9)
    with pytest.raises(ShapeError, match="new_T_ij"):
        edge_consistency(T0, i, j, T_ij, info, 0, 3, eye[:3], info[0], 0.9)


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 7, 12, 50])
def test_chi2_quantile_matches_scipy(dof):
    stats = pytest.importorskip("scipy.stats")
    rtol = 1e-13 if dof <= 12 else 1e-8
    for p in [1e-6, 0.001, 0.05, 0.3, 0.5, 0.7, 0.9, 0.99, 0.999, 0.9999, 1 - 1e-7]:
        assert chi2_quantile(p, dof) == pytest.approx(float(stats.chi2.ppf(p, dof)), rel=rtol), p


def test_chi2_quantile_rejects_bad_arguments_and_needs_no_scipy():
    import subprocess
    import sys

    from torchslam.errors import InvalidValueError

    for p in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(InvalidValueError, match="probability"):
            chi2_quantile(p, 6)
    with pytest.raises(InvalidValueError, match="dof"):
        chi2_quantile(0.99, 0)
    # SciPy's statistics module took 0.4-0.9 s to import at a run's first loop test.
    code = ("import sys; from torchslam.backend import chi2_quantile; chi2_quantile(0.999, 6); "
            "print(sorted(m for m in sys.modules if m.startswith('scipy.stats')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
