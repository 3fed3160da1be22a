"""FastGO linearisation from statistics against linearising every correspondence (float64)."""

from __future__ import annotations

import pytest
import torch

from torchslam.errors import ShapeError
from torchslam.fastgo import PairStats, assemble, linearize, pair_cost
from torchslam.geometry import se3_exp

from tests._references import reference_linearize

FIELDS = ("H_ii", "H_ij", "H_jj", "g_i", "g_j", "cost")


def random_problem(seed: int, n_nodes=8, n_pairs=25, far=3.0):
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([far, far, far, 1, 1, 1], dtype=torch.float64)
    T = se3_exp(torch.randn(n_nodes, 6, generator=g, dtype=torch.float64) * scale)
    pairs = torch.randint(0, n_nodes, (n_pairs, 2), generator=g)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    sizes = torch.randint(1, 60, (pairs.shape[0],), generator=g).tolist()
    pi = [torch.randn(k, 3, generator=g, dtype=torch.float64) + torch.tensor([0, 0, 3.0], dtype=torch.float64) for k in sizes]
    pj = [torch.randn(k, 3, generator=g, dtype=torch.float64) for k in sizes]
    w = [torch.rand(k, generator=g, dtype=torch.float64) for k in sizes]
    return T, pairs, pi, pj, w


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("weighted", [False, True])
def test_linearize_equals_per_correspondence_reference(seed, weighted):
    T, pairs, pi, pj, w = random_problem(seed)
    weights = w if weighted else None
    fast = linearize(T, pairs, PairStats.from_correspondences(pi, pj, weights))
    ref = reference_linearize(T, pairs, pi, pj, weights)
    for f in FIELDS:
        a, b = getattr(fast, f), getattr(ref, f)
        assert (a - b).abs().max() <= 1e-9 * b.abs().max(), f
    assert torch.allclose(fast.H_ii, fast.H_ii.mT) and torch.allclose(fast.g_j, -fast.g_i)


def test_gradient_is_derivative_of_cost_under_left_perturbation():
    # Independent of the Jacobian formulas: d/de cost(exp(e d) T) = 2 g . d
    T, pairs, pi, pj, w = random_problem(3, n_nodes=4, n_pairs=6)
    st = PairStats.from_correspondences(pi, pj, w)
    H, g = assemble(linearize(T, pairs, st), pairs, 4)
    gen = torch.Generator().manual_seed(9)
    d = torch.randn(4, 6, generator=gen, dtype=torch.float64)
    eps = 1e-6

    def c(e):
        return pair_cost(se3_exp(e * d) @ T, pairs, st).sum()

    fd = (c(eps) - c(-eps)) / (2 * eps)
    assert torch.allclose(fd, 2 * (g * d).sum(), rtol=1e-6)
    # Gauss-Newton curvature: at an exact fit (zero residual) J^T J is the exact Hessian / 2.
    T2 = T.clone()
    T2[1] = T2[0]
    same = torch.tensor([[0, 1]])
    st2 = PairStats.from_correspondences([pi[0]], [pi[0]])
    H2, g2 = assemble(linearize(T2, same, st2), same, 4)

    def c2(e):
        return pair_cost(se3_exp(e * d) @ T2, same, st2).sum()

    dd = c2(eps) + c2(-eps) - 2 * c2(0.0)
    assert torch.allclose(dd / eps**2, 2 * (d.reshape(-1) @ H2.to_dense() @ d.reshape(-1)), rtol=1e-4)
    assert g2.abs().max() < 1e-9


def test_far_from_origin_cost_keeps_precision():
    T, pairs, pi, pj, w = random_problem(4, far=500.0)
    st = PairStats.from_correspondences(pi, pj, w)
    ref = reference_linearize(T, pairs, pi, pj, w)
    assert ((pair_cost(T, pairs, st) - ref.cost).abs() <= 1e-9 * ref.cost.abs().max()).all()


def test_float32_inputs_and_bad_shapes():
    T, pairs, pi, pj, _ = random_problem(5)
    st = PairStats.from_correspondences(pi, pj)
    lin32 = linearize(T.float(), pairs, st)
    assert lin32.H_ij.dtype == torch.float32
    with pytest.raises(ShapeError, match="pairs"):
        linearize(T, pairs[:-1], st)
    with pytest.raises(ShapeError, match="int64"):
        linearize(T, pairs.int(), st)
    with pytest.raises(ShapeError, match="T_wc"):
        linearize(T[:, :3], pairs, st)


def test_residual_curvature_completes_the_exact_hessian():
    # Hessian of c(delta) = cost(exp(delta) T) by autograd equals 2 (J^T J + S) at delta = 0.
    from torchslam.fastgo import residual_curvature
    from torchslam.optim import BlockSparseMatrix

    T, pairs, pi, pj, w = random_problem(6, n_nodes=4, n_pairs=7)
    st = PairStats.from_correspondences(pi, pj, w)
    H, _ = assemble(linearize(T, pairs, st), pairs, 4)
    S_i, S_j = residual_curvature(T, pairs, st)
    diag = H.diag.index_add(0, pairs[:, 0], S_i).index_add(0, pairs[:, 1], S_j)
    exact = BlockSparseMatrix(diag, H.off, H.rows, H.cols).to_dense()

    def c(d):
        return pair_cost(se3_exp(d.reshape(4, 6)) @ T, pairs, st).sum()

    hess = torch.autograd.functional.hessian(c, torch.zeros(24, dtype=torch.float64))
    assert torch.allclose(hess, 2 * exact, atol=1e-9 * hess.abs().max())
    assert not torch.allclose(hess, 2 * H.to_dense(), atol=1e-3 * hess.abs().max())
