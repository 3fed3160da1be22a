"""The level-scheduled block Cholesky: the same factor and solution as the front-by-front one, with
one batched call per level of the elimination tree."""

from __future__ import annotations

import pytest
import torch
from torch.overrides import TorchFunctionMode

from torchslam.diagnostics import count_syncs
from torchslam.errors import ConfigError
from torchslam.optim import BlockSparseMatrix, Schedule, analyze, block_cholesky, solve_block_sparse

from tests.optim.test_blocksparse import chain_with_loops, dense_reference, random_system


def _chain(n, g):
    return chain_with_loops(n, g, 0)


def _loops(n, g):
    return chain_with_loops(n, g, n // 4)


def _random_pose_graph(n, g):
    # a spanning chain plus random edges anywhere: a wide profile, many fronts per level
    return chain_with_loops(n, g, 2 * n)


def _forest(n, g):
    # disconnected trees (random parents) and an isolated node
    parts, off = [], 0
    for size in (n // 2, n // 3, 1, n - n // 2 - n // 3 - 1):
        if size > 1:
            parent = (torch.rand(size - 1, generator=g) * torch.arange(1, size)).floor().to(torch.int64)
            parts.append(torch.stack([parent, torch.arange(1, size)], -1) + off)
        off += size
    return torch.cat(parts)


GRAPHS = {"chain": _chain, "loops": _loops, "random": _random_pose_graph, "forest": _forest}


def _fixed(n: int) -> torch.Tensor:
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    return fixed


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


@pytest.mark.parametrize("ordering, leaf", [("band", 4), ("band", 16), ("nested", 1), ("nested", 6)])
@pytest.mark.parametrize("graph", sorted(GRAPHS))
def test_level_schedule_matches_front_schedule(graph, ordering, leaf):
    g = torch.Generator().manual_seed(len(graph) * 7 + leaf)
    n = 90
    A = random_system(n, GRAPHS[graph](n, g), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    sym = analyze(n, A.rows, A.cols, _fixed(n), leaf_size=leaf, ordering=ordering)
    front, level = block_cholesky(A, sym), block_cholesky(A, sym, schedule="level")
    assert level.schedule is Schedule.LEVEL and front.schedule is Schedule.FRONT
    for (L1, U1), (L2, U2) in zip(front.fronts(), level.fronts(), strict=True):
        assert L1.shape == L2.shape and U1.shape == U2.shape
        assert _rel(L2, L1) < 1e-12
        if U1.numel():
            assert _rel(U2, U1) < 1e-12
    x1, x2 = front.solve(rhs), level.solve(rhs)
    assert _rel(x2, x1) < 1e-12
    assert torch.equal(front.ok, level.ok) and level.ok.all()
    assert torch.all(x2[0] == 0)
    ref = dense_reference(A, rhs, _fixed(n))
    assert torch.allclose(x2, ref, rtol=0, atol=1e-9 * ref.abs().max())


def test_failing_pivot_is_reported_and_isolated_by_levels():
    g = torch.Generator().manual_seed(5)
    good = random_system(40, _random_pose_graph(40, g), g)
    bad = random_system(30, _loops(30, g), g)
    bad = BlockSparseMatrix(bad.diag - 1e4 * torch.eye(6, dtype=torch.float64), bad.off, bad.rows, bad.cols)
    A, _ = BlockSparseMatrix.cat([good, bad])
    rhs = torch.randn(70, 6, generator=g, dtype=torch.float64)
    fixed = torch.zeros(70, dtype=torch.bool)
    fixed[[0, 40]] = True
    sym = analyze(70, A.rows, A.cols, fixed, leaf_size=2, ordering="nested")
    front, level = block_cholesky(A, sym), block_cholesky(A, sym, schedule="level")
    assert torch.equal(front.ok, level.ok)
    assert level.ok[:40].all() and not level.ok[41:].any() and level.ok[40]
    # fronts of the failing problem share levels with the good one's: padding keeps them apart
    groups = sym._plan()["group"]
    good_fronts = [k for k, s in enumerate(sym._s_dofs) if s[0] < 40 * 6]
    bad_fronts = [k for k, s in enumerate(sym._s_dofs) if s[0] >= 40 * 6]
    assert set(groups[good_fronts]) & set(groups[bad_fronts])
    x = level.solve(rhs)
    ref = dense_reference(good, rhs[:40], fixed[:40])
    assert torch.allclose(x[:40], ref, rtol=0, atol=1e-9 * ref.abs().max())
    assert torch.allclose(x[:40], front.solve(rhs)[:40], rtol=0, atol=1e-12 * ref.abs().max())


class _CountCalls(TorchFunctionMode):
    """Count the dense factorisation and triangular-solve calls."""

    def __init__(self):
        super().__init__()
        self.calls = {"cholesky": 0, "solve_triangular": 0}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is torch.linalg.cholesky_ex:
            self.calls["cholesky"] += 1
        elif func is torch.linalg.solve_triangular:
            self.calls["solve_triangular"] += 1
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("graph", ["random", "forest", "loops"])
def test_launches_follow_the_tree_depth(graph):
    g = torch.Generator().manual_seed(3)
    n = 200
    A = random_system(n, GRAPHS[graph](n, g), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    sym = analyze(n, A.rows, A.cols, _fixed(n), leaf_size=4, ordering="nested")
    # a level's fronts come in a few size classes: calls grow with the depth, not the fronts
    assert sym.depth <= sym.num_groups <= 4 * sym.depth < sym.num_fronts
    for schedule, per_pass in (("front", sym.num_fronts), ("level", sym.num_groups)):
        with _CountCalls() as factor_calls:
            fac = block_cholesky(A, sym, schedule=schedule)
        with _CountCalls() as solve_calls:
            fac.solve(rhs)
        assert factor_calls.calls["cholesky"] == per_pass
        # one off-diagonal solve per front / group with an update block (all but the roots)
        assert factor_calls.calls["solve_triangular"] <= per_pass
        assert solve_calls.calls == {"cholesky": 0, "solve_triangular": 2 * per_pass}


def test_launches_equal_the_depth_for_fronts_of_one_size():
    # a binary tree of 2^5 - 1 single-node supernodes, each with two neighbours above it at most:
    # every level is one size class, so the level schedule makes one call per level
    g = torch.Generator().manual_seed(4)
    n = 31
    child = torch.arange(1, n)
    A = random_system(n, torch.stack([(child - 1) // 2, child], -1), g)
    sym = analyze(n, A.rows, A.cols, leaf_size=1, ordering="nested")
    assert sym.num_groups == sym.depth < sym.num_fronts
    with _CountCalls() as calls:
        block_cholesky(A, sym, schedule="level").solve(torch.ones(n, 6, dtype=torch.float64))
    assert calls.calls["cholesky"] == sym.depth
    assert calls.calls["solve_triangular"] == 3 * sym.depth - 1  # the root level has no coupling block


@pytest.mark.parametrize("schedule", ["front", "level"])
def test_factor_and_solve_do_not_synchronise(schedule):
    g = torch.Generator().manual_seed(8)
    n = 60
    A = random_system(n, _loops(n, g), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    sym = analyze(n, A.rows, A.cols, _fixed(n), leaf_size=4, ordering="nested")
    block_cholesky(A, sym, schedule).solve(rhs)  # index tensors are copied to the device once
    with count_syncs() as syncs:
        fac = block_cholesky(A, sym, schedule)
        fac.solve(rhs)
        fac.ok.logical_not()
    assert syncs.count == 0, syncs.summary()


@pytest.mark.parametrize("ordering", ["band", "nested"])
def test_gradients_through_the_level_schedule(ordering):
    g = torch.Generator().manual_seed(6)
    n = 9
    A = random_system(n, _loops(n, g), g)
    sym = analyze(n, A.rows, A.cols, _fixed(n), leaf_size=2, ordering=ordering)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64, requires_grad=True)
    off = A.off.clone().requires_grad_(True)
    diag = A.diag.clone().requires_grad_(True)

    def f(schedule):
        def solve(rhs_, off_, diag_):
            # a symmetric matrix's diagonal blocks: the factorisation reads one triangle
            M = BlockSparseMatrix(0.5 * (diag_ + diag_.transpose(1, 2)), off_ * 0.1, A.rows, A.cols)
            return block_cholesky(M, sym, schedule).solve(rhs_)
        return solve

    assert torch.autograd.gradcheck(lambda r, o: f("level")(r, o, A.diag), (rhs, off), eps=1e-6, atol=1e-6)
    w = torch.randn(n, 6, generator=g, dtype=torch.float64)
    grads = [torch.autograd.grad((f(s)(rhs, off, diag) * w).sum(), (rhs, off, diag)) for s in ("front", "level")]
    for a, b in zip(*grads):
        assert _rel(b, a) < 1e-12


def test_solve_block_sparse_takes_the_schedule():
    g = torch.Generator().manual_seed(9)
    n = 30
    A = random_system(n, _loops(n, g), g)
    rhs = torch.randn(n, 6, generator=g, dtype=torch.float64)
    x1, ok1 = solve_block_sparse(A, rhs, _fixed(n))
    x2, ok2 = solve_block_sparse(A, rhs, _fixed(n), schedule=Schedule.LEVEL)
    assert _rel(x2, x1) < 1e-12 and torch.equal(ok1, ok2)
    with pytest.raises(ConfigError, match=r"schedule: 'tree' is not one of \['front', 'level'\]"):
        block_cholesky(A, analyze(n, A.rows, A.cols), schedule="tree")


def test_everything_fixed_gives_zero():
    g = torch.Generator().manual_seed(10)
    A = random_system(3, _chain(3, g), g)
    sym = analyze(3, A.rows, A.cols, torch.ones(3, dtype=torch.bool))
    assert sym.num_fronts == 0 and sym.depth == 0
    fac = block_cholesky(A, sym, "level")
    assert fac.ok.all() and torch.all(fac.solve(torch.ones(3, 6, dtype=torch.float64)) == 0)


def test_optimisers_take_the_schedule():
    from torchslam.fastgo import FastGOConfig, optimize
    from torchslam.fastgo.synthetic import loop_route_problem

    prob = loop_route_problem(40, noise=0.005, seed=1)
    res = {s: optimize(prob.T_init, prob.pairs, prob.stats, ordering="nested", schedule=s) for s in ("front", "level")}
    assert res["level"].iterations == res["front"].iterations
    assert torch.allclose(res["level"].T_wc, res["front"].T_wc, rtol=0, atol=1e-10)
    assert FastGOConfig(schedule="LEVEL").lm().schedule is Schedule.LEVEL
    with pytest.raises(ConfigError, match="schedule"):
        FastGOConfig(schedule="tree")
