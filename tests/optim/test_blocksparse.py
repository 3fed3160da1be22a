"""Block-sparse normal-equation solves: supernodal Cholesky, dense and PCG against dense LAPACK."""

from __future__ import annotations

import pytest
import torch

from torchslam.errors import ConfigError, InvalidValueError, ShapeError
from torchslam.optim import (
    BlockSparseMatrix,
    SolverMethod,
    analyze,
    block_cholesky,
    pcg_block_jacobi,
    solve_block_sparse,
)


def random_system(n: int, edges: torch.Tensor, g: torch.Generator, b: int = 6) -> BlockSparseMatrix:
    """SPD block system: sum over edges of J^T J with random 2b x 2b... Jacobians, plus a ridge."""
    E = edges.shape[0]
    J = torch.randn(E, 2 * b + 3, 2 * b, generator=g, dtype=torch.float64)
    Hp = J.mT @ J
    diag = torch.zeros(n, b, b, dtype=torch.float64)
    diag = diag.index_add(0, edges[:, 0], Hp[:, :b, :b]).index_add(0, edges[:, 1], Hp[:, b:, b:])
    diag = diag + 1e-3 * torch.eye(b, dtype=torch.float64)
    return BlockSparseMatrix(diag, Hp[:, :b, b:].contiguous(), edges[:, 0].contiguous(), edges[:, 1].contiguous())


def chain_with_loops(n: int, g: torch.Generator, loops: int) -> torch.Tensor:
    chain = torch.stack([torch.arange(n - 1), torch.arange(1, n)], -1)
    a = torch.randint(0, n, (loops,), generator=g)
    c = torch.randint(0, n, (loops,), generator=g)
    keep = a != c
    return torch.cat([chain, torch.stack([a[keep], c[keep]], -1)])


def dense_reference(A: BlockSparseMatrix, rhs: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
    free = (~fixed).repeat_interleave(A.block_size)
    D = A.to_dense()[free][:, free]
    x = torch.zeros(rhs.numel(), dtype=rhs.dtype)
    x[free] = torch.linalg.solve(D, rhs.reshape(-1)[free])
    return x.reshape(rhs.shape)


@pytest.mark.parametrize("ordering", ["band", "nested"])
@pytest.mark.parametrize("n,loops,leaf", [(5, 2, 48), (120, 30, 8), (300, 60, 16), (80, 20, 1)])
def test_cholesky_matches_dense(n, loops, leaf, ordering):
    g = torch.Generator().manual_seed(n)
    A = random_system(n, chain_with_loops(n, g, loops), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    sym = analyze(n, A.rows, A.cols, fixed, leaf_size=leaf, ordering=ordering)
    fac = block_cholesky(A, sym)
    x = fac.solve(rhs)
    ref = dense_reference(A, rhs, fixed)
    assert fac.ok.all()
    assert torch.allclose(x, ref, rtol=0, atol=1e-9 * ref.abs().max())
    assert torch.all(x[0] == 0)
    if n > leaf:
        assert sym.num_fronts > 1  # the dissection really split the graph


def test_to_dense_and_matvec_agree():
    g = torch.Generator().manual_seed(1)
    A = random_system(7, chain_with_loops(7, g, 3), g)
    x = torch.randn(7, 6, generator=g, dtype=torch.float64)
    assert torch.allclose(A.matvec(x).reshape(-1), A.to_dense() @ x.reshape(-1))
    assert torch.allclose(A.to_dense(), A.to_dense().T)


def test_duplicate_blocks_add_up():
    g = torch.Generator().manual_seed(2)
    edges = torch.tensor([[0, 1], [1, 2], [0, 1], [1, 0]])
    A = random_system(3, edges, g)
    rhs = torch.randn(3, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(3, dtype=torch.bool)
    x, ok = solve_block_sparse(A, rhs, fixed)
    assert ok.all()
    assert torch.allclose(x, dense_reference(A, rhs, fixed), atol=1e-10)


def test_dense_and_pcg_methods_match_cholesky():
    g = torch.Generator().manual_seed(3)
    n = 40
    A = random_system(n, chain_with_loops(n, g, 10), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[3] = True
    ref = dense_reference(A, rhs, fixed)
    xd, okd = solve_block_sparse(A, rhs, fixed, method="dense")
    xp, okp = solve_block_sparse(A, rhs, fixed, method=SolverMethod.PCG, pcg_tol=1e-12, pcg_max_iter=5000)
    assert okd.all() and okp.all()
    assert torch.allclose(xd, ref, atol=1e-9)
    assert torch.allclose(xp, ref, atol=1e-7)
    x, conv, its = pcg_block_jacobi(A, rhs, fixed, tol=1e-12, max_iter=5000)
    assert bool(conv) and its > 1 and torch.all(x[3] == 0)


@pytest.mark.parametrize("leaf", [1, 3, 16])
def test_band_order_keeps_components_apart(leaf):
    # three chains with loops, an isolated node and a fixed node in the middle of one chain;
    # the band order must match dense LAPACK and never put two components in one supernode
    g = torch.Generator().manual_seed(leaf)
    parts, off = [], 0
    for n in (23, 1, 40, 9):
        if n > 1:
            parts.append(chain_with_loops(n, g, n // 3) + off)
        off += n
    edges = torch.cat(parts)
    n = off
    A = random_system(n, edges, g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[[0, 40]] = True
    sym = analyze(n, A.rows, A.cols, fixed, leaf_size=leaf, ordering="band")
    fac = block_cholesky(A, sym)
    ref = dense_reference(A, rhs, fixed)
    assert fac.ok.all()
    assert torch.allclose(fac.solve(rhs), ref, rtol=0, atol=1e-9 * ref.abs().max())
    comp = torch.repeat_interleave(torch.arange(4), torch.tensor([23, 1, 40, 9]))
    for s_dofs in sym._s_dofs:
        assert comp[torch.as_tensor(s_dofs) // 6].unique().numel() == 1
    assert all(s <= leaf for s, _ in sym.front_sizes)


@pytest.mark.parametrize("ordering", ["band", "nested"])
def test_autograd_and_in_place_paths_agree_with_dense(ordering):
    # without autograd the factorisation works in place on lower triangles and writes most
    # Schur updates straight into the next front; with autograd it builds whole fronts out
    # of place; both must give the dense solution
    g = torch.Generator().manual_seed(11)
    n = 150
    A = random_system(n, chain_with_loops(n, g, 40), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[3] = True
    sym = analyze(n, A.rows, A.cols, fixed, leaf_size=6, ordering=ordering)
    if ordering == "band":
        assert any(p >= 0 for p in sym._direct)  # the in-place update path is exercised
    ref = dense_reference(A, rhs, fixed)
    x_fast = block_cholesky(A, sym).solve(rhs)
    off = A.off.clone().requires_grad_(True)
    x_grad = block_cholesky(BlockSparseMatrix(A.diag, off, A.rows, A.cols), sym).solve(rhs)
    assert x_grad.requires_grad
    tol = 1e-9 * ref.abs().max()
    assert torch.allclose(x_fast, ref, rtol=0, atol=tol)
    assert torch.allclose(x_grad.detach(), ref, rtol=0, atol=tol)


def test_batched_concatenation_equals_per_problem():
    g = torch.Generator().manual_seed(4)
    systems, rhss, fixeds = [], [], []
    for n in (4, 50, 17):
        systems.append(random_system(n, chain_with_loops(n, g, n // 4), g))
        rhss.append(torch.randn(n, 6, generator=g, dtype=torch.float64))
        f = torch.zeros(n, dtype=torch.bool)
        f[0] = True
        fixeds.append(f)
    A, offsets = BlockSparseMatrix.cat(systems)
    x, ok = solve_block_sparse(A, torch.cat(rhss), torch.cat(fixeds))
    assert ok.all()
    for b, (S, r, f) in enumerate(zip(systems, rhss, fixeds)):
        xb, _ = solve_block_sparse(S, r, f)
        assert torch.allclose(x[offsets[b]:offsets[b + 1]], xb, atol=1e-10)


def test_indefinite_problem_is_reported_and_isolated():
    g = torch.Generator().manual_seed(5)
    good = random_system(10, chain_with_loops(10, g, 3), g)
    bad = random_system(6, chain_with_loops(6, g, 2), g)
    bad = BlockSparseMatrix(bad.diag - 1e4 * torch.eye(6, dtype=torch.float64), bad.off, bad.rows, bad.cols)
    A, offsets = BlockSparseMatrix.cat([good, bad])
    rhs = torch.randn(16, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(16, dtype=torch.bool)
    fixed[0] = True
    fixed[10] = True
    x, ok = solve_block_sparse(A, rhs, fixed)
    assert ok[:10].all() and not ok[11:].any()
    ref = dense_reference(good, rhs[:10], fixed[:10])
    assert torch.allclose(x[:10], ref, atol=1e-9)


def test_gradients_through_the_sparse_solve():
    g = torch.Generator().manual_seed(6)
    n = 5
    A = random_system(n, chain_with_loops(n, g, 2), g)
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    sym = analyze(n, A.rows, A.cols, fixed, leaf_size=2)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64, requires_grad=True)
    off = A.off.clone().requires_grad_(True)

    def f(rhs_, off_):
        M = BlockSparseMatrix(A.diag, off_ * 0.1, A.rows, A.cols)
        return block_cholesky(M, sym).solve(rhs_)

    assert torch.autograd.gradcheck(f, (rhs, off), eps=1e-6, atol=1e-6)


def test_bad_inputs_raise():
    g = torch.Generator().manual_seed(7)
    A = random_system(4, chain_with_loops(4, g, 1), g)
    with pytest.raises(ShapeError, match="rhs"):
        solve_block_sparse(A, torch.zeros(4, 3, dtype=torch.float64))
    with pytest.raises(ConfigError, match=r"solver method: 'qr' is not one of \['auto', 'cholesky', 'dense', 'pcg'\]"):
        solve_block_sparse(A, torch.zeros(4, 6, dtype=torch.float64), method="qr")
    with pytest.raises(InvalidValueError, match="rows/cols"):
        analyze(3, torch.tensor([0, 5]), torch.tensor([1, 2]))
    with pytest.raises(ConfigError, match=r"ordering: 'amd' is not one of \['band', 'nested'\]"):
        analyze(4, A.rows, A.cols, ordering="amd")
    with pytest.raises(ConfigError, match="leaf_size"):
        analyze(4, A.rows, A.cols, leaf_size=0)
    with pytest.raises(ShapeError, match="off"):
        BlockSparseMatrix(A.diag, A.off[:, :3], A.rows, A.cols)
    sym = analyze(4, A.rows[:1], A.cols[:1])
    with pytest.raises(ShapeError, match="off-diagonal blocks"):
        block_cholesky(A, sym)
