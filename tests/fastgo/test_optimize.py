"""FastGO optimisation: planted solutions, per-correspondence GN, batching, robustness,
degenerate input and gradients through unrolled iterations."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.errors import ConfigError, ShapeError
from torchslam.fastgo import (
    FastGOConfig,
    FastGOProblem,
    PairStats,
    PairStatus,
    assemble,
    optimize,
    optimize_batch,
)
from torchslam.fastgo.synthetic import loop_route_problem, make_correspondences
from torchslam.geometry import se3_exp, se3_inverse, se3_log

from tests._references import reference_linearize


def pose_error(A: torch.Tensor, B: torch.Tensor) -> float:
    return float(se3_log(se3_inverse(A) @ B).abs().max())


def test_planted_drift_and_loop_return_to_ground_truth():
    P = loop_route_problem(40, lap_length=20, loops_per_keyframe=1, noise=0.0, seed=1)
    assert pose_error(P.T_init, P.T_gt) > 0.05  # the odometry really drifted
    res = optimize(P.T_init, P.pairs, P.stats)
    assert res.converged and res.iterations < 10
    assert pose_error(res.T_wc, P.T_gt) < 1e-8
    assert res.T_wc.dtype == torch.float64 and torch.equal(res.T_wc[0], P.T_init[0])
    assert res.cost[-1] < 1e-12 * res.cost[0] and torch.all(res.cost[1:] <= res.cost[:-1] + 1e-12 * res.cost[0])
    assert (res.pair_status == int(PairStatus.OK)).all() and not res.disconnected.any()


def test_matches_per_correspondence_gauss_newton():
    P = loop_route_problem(24, lap_length=8, noise=0.02, correspondences=12, keep_points=True, seed=2)
    pi, pj = list(P.points_i), list(P.points_j)
    T = P.T_init.clone()
    n = T.shape[0]
    free = torch.ones(6 * n, dtype=torch.bool)
    free[:6] = False
    for _ in range(15):  # plain GN, every correspondence linearised, dense solve
        H, g = assemble(reference_linearize(T, P.pairs, pi, pj), P.pairs, n)
        x = torch.zeros(6 * n, dtype=torch.float64)
        x[free] = torch.linalg.solve(H.to_dense()[free][:, free], -g.reshape(-1)[free])
        T = se3_exp(x.reshape(n, 6)) @ T
    res = optimize(P.T_init, P.pairs, P.stats, tol=1e-14, iterations=30)
    assert res.converged
    assert pose_error(res.T_wc, T) < 1e-8


def test_batched_equals_per_problem():
    probs = [loop_route_problem(n, lap_length=l, noise=0.01, seed=s) for n, l, s in [(30, 10, 3), (9, 8, 4), (55, 20, 5)]]
    fixed = [0, 4, 10]
    inits = [p.T_init for p in probs]
    # problem 1 starts at its optimum: it must stop after one step while the others go on
    inits[1] = optimize(probs[1].T_init, probs[1].pairs, probs[1].stats, fixed=4, tol=1e-14).T_wc
    batch = optimize_batch([FastGOProblem(T, p.pairs, p.stats, f) for T, p, f in zip(inits, probs, fixed)])
    assert len(batch) == 3 and batch.converged.all()
    for b, (T0, p, f) in enumerate(zip(inits, probs, fixed)):
        single = optimize(T0, p.pairs, p.stats, fixed=f)
        mine = batch.problem(b)
        assert pose_error(mine.T_wc, single.T_wc) < 1e-9
        assert mine.iterations == single.iterations
        assert torch.equal(mine.T_wc[f], T0[f])
    # each problem keeps its own iteration count (no shared batch-mean stopping)
    assert int(batch.iterations[1]) == 1 and int(batch.iterations[0]) > 1


def test_solvers_agree():
    P = loop_route_problem(30, lap_length=10, noise=0.01, seed=6)
    a = optimize(P.T_init, P.pairs, P.stats, solver="cholesky", leaf_size=4)
    b = optimize(P.T_init, P.pairs, P.stats, solver="dense")
    c = optimize(P.T_init, P.pairs, P.stats, solver="pcg")
    assert pose_error(a.T_wc, b.T_wc) < 1e-9 and pose_error(c.T_wc, b.T_wc) < 1e-6


def chain_with_false_loop(seed: int = 7):
    """A straight chain whose two ends are joined by a wrong loop pair."""
    P = loop_route_problem(24, lap_length=1000, loops_per_keyframe=0, noise=0.003, seed=seed, drift_rot=0, drift_trans=0)
    g = torch.Generator().manual_seed(seed)
    wrong = P.T_gt.clone()
    wrong[23] = se3_exp(torch.tensor([0.6, -0.3, 0.2, 0.0, 0.2, 0.1], dtype=torch.float64)) @ wrong[23]
    loop = torch.tensor([[0, 23]])
    li, lj = make_correspondences(wrong, loop, 32, 0.003, g)
    pairs = torch.cat([P.pairs, loop])
    stats = PairStats.cat([P.stats, PairStats.from_padded(li, lj)])
    return P, pairs, stats


def test_robust_reweighting_keeps_false_loop_from_bending_the_map():
    P, pairs, stats = chain_with_false_loop()
    plain = optimize(P.T_gt, pairs, stats)
    assert pose_error(plain.T_wc, P.T_gt) > 0.05  # least squares bends the whole chain
    for kernel in ("cauchy", "geman_mcclure"):
        robust = optimize(P.T_gt, pairs, stats, robust=kernel, robust_scale=0.02)
        assert robust.converged
        assert float(robust.pair_weights[-1]) < 1e-2  # the false loop is switched off
        assert float(robust.pair_weights[:-1].min()) > 0.5  # the true pairs are kept (RMS ~ 7 mm)
        assert pose_error(robust.T_wc, P.T_gt) < 0.02
    huber = optimize(P.T_gt, pairs, stats, robust="huber", robust_scale=0.02)
    assert float(huber.pair_weights[-1]) < 0.1
    assert pose_error(huber.T_wc, P.T_gt) < pose_error(plain.T_wc, P.T_gt)


def test_degenerate_pairs_are_excluded_and_reported():
    P = loop_route_problem(12, lap_length=6, noise=0.0, seed=8, keep_points=True)
    line = torch.linspace(0, 1, 10, dtype=torch.float64)[:, None] * torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    bad_i = [P.points_i[0][:2], line + 1, P.points_i[2].clone(), P.points_i[3]]
    bad_j = [P.points_j[0][:2], line, P.points_j[2], P.points_j[3]]
    bad_i[2][5, 1] = float("nan")
    extra = PairStats.from_correspondences(bad_i, bad_j)
    # pair 3 repeats pair 3 of the problem; pairs 0-2 get wrong geometry that would hurt if used
    pairs = torch.cat([P.pairs, torch.tensor([[0, 5], [1, 7], [2, 9], P.pairs[3].tolist()])])
    stats = PairStats.cat([P.stats, extra])
    res = optimize(P.T_init, pairs, stats)
    M = P.pairs.shape[0]
    assert res.pair_status[M:].tolist() == [PairStatus.TOO_FEW, PairStatus.COLLINEAR, PairStatus.NONFINITE, PairStatus.DUPLICATE]
    assert torch.isfinite(res.T_wc).all() and res.converged
    assert pose_error(res.T_wc, P.T_gt) < 1e-8
    assert torch.isnan(res.pair_rms[M:M + 3]).all() and torch.all(res.pair_weights[M:] == 0)


def test_duplicate_pairs_merge_like_one_pair():
    P = loop_route_problem(10, lap_length=5, noise=0.02, seed=9, keep_points=True)
    half = P.points_i.shape[1] // 2
    a = PairStats.from_padded(P.points_i[:, :half], P.points_j[:, :half])
    b = PairStats.from_padded(P.points_j[:, half:], P.points_i[:, half:])  # reversed orientation
    pairs = torch.cat([P.pairs, P.pairs.flip(-1)])
    res = optimize(P.T_init, pairs, PairStats.cat([a, b]))
    ref = optimize(P.T_init, P.pairs, P.stats)
    assert (res.pair_status[P.pairs.shape[0]:] == int(PairStatus.DUPLICATE)).all()
    assert pose_error(res.T_wc, ref.T_wc) < 1e-9


def test_disconnected_keyframes_are_reported_not_nan():
    P = loop_route_problem(10, lap_length=5, noise=0.0, seed=10)
    keep = (P.pairs != 9).all(-1) & ~((P.pairs >= 6).all(-1) & (P.pairs.min(-1).values < 9) & False)
    # keyframe 9 loses all its pairs; keyframes 6-8 lose their links to 0-5
    keep = keep & ~((P.pairs < 6).any(-1) & (P.pairs >= 6).any(-1))
    res = optimize(P.T_init, P.pairs[keep], P.stats[keep])
    assert res.disconnected.tolist() == [False] * 6 + [True] * 4
    assert torch.isfinite(res.T_wc).all() and res.converged
    assert torch.equal(res.T_wc[9], P.T_init[9]) and torch.equal(res.T_wc[6], P.T_init[6])
    # the floating part is still optimised relative to its own gauge (keyframe 6)
    rel = se3_inverse(res.T_wc[6]) @ res.T_wc[8]
    assert pose_error(rel, se3_inverse(P.T_gt[6]) @ P.T_gt[8]) < 1e-8


def test_invalid_pairs_and_options_raise():
    P = loop_route_problem(6, lap_length=3, seed=11)
    with pytest.raises(ShapeError, match="with itself"):
        optimize(P.T_init, torch.cat([P.pairs[:-1], torch.tensor([[2, 2]])]), P.stats)
    with pytest.raises(ShapeError, match="outside"):
        optimize(P.T_init, torch.cat([P.pairs[:-1], torch.tensor([[2, 6]])]), P.stats)
    with pytest.raises(ShapeError, match="fixed"):
        optimize(P.T_init, P.pairs, P.stats, fixed=6)
    with pytest.raises(ConfigError, match="unknown option"):
        optimize(P.T_init, P.pairs, P.stats, iteratons=3)
    with pytest.raises(ConfigError, match=r"'welsch' is not one of \['l2', 'huber'"):
        FastGOConfig(robust="welsch")


def _tiny():
    P = loop_route_problem(4, lap_length=100, local_pairs=2, noise=0.05, correspondences=8, seed=12)
    return P


def _unrolled(P, w):
    res = optimize(P.T_init, P.pairs, P.stats, pair_weights=w, iterations=2, tol=0.0, step_tol=0.0, damping=0.0, solver="cholesky")
    return res.T_wc[1:, :3, :].reshape(-1)


def test_gradcheck_poses_wrt_pair_weights():
    P = _tiny()
    w = torch.linspace(0.5, 1.5, P.pairs.shape[0], dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda w_: _unrolled(P, w_), (w,), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_weight_gradient_matches_finite_differences_at_convergence():
    P = loop_route_problem(8, lap_length=4, noise=0.03, correspondences=10, seed=13)
    m = P.pairs.shape[0]
    w = torch.ones(m, dtype=torch.float64, requires_grad=True)

    def loss(w_):
        # a fixed number of GN steps (negative tolerances never stop early): the unrolled
        # gradient then equals the derivative of the converged optimum
        res = optimize(P.T_init, P.pairs, P.stats, pair_weights=w_, iterations=25, tol=-1.0, step_tol=-1.0, damping=0.0)
        return (res.T_wc[:, :3, 3] - P.T_gt[:, :3, 3]).square().sum()

    (grad,) = torch.autograd.grad(loss(w), w)
    eps = 1e-5
    for k in (0, m // 2, m - 1):
        e = torch.zeros(m, dtype=torch.float64)
        e[k] = eps
        fd = (loss(w.detach() + e) - loss(w.detach() - e)) / (2 * eps)
        assert math.isclose(float(grad[k]), float(fd), rel_tol=1e-4, abs_tol=1e-10)


def test_no_usable_pair_leaves_poses_unchanged():
    T = se3_exp(torch.randn(3, 6, generator=torch.Generator().manual_seed(14), dtype=torch.float64))
    pts = torch.randn(1, 2, 3, dtype=torch.float64)
    res = optimize(T, torch.tensor([[0, 1]]), PairStats.from_padded(pts, pts))
    assert res.pair_status.tolist() == [PairStatus.TOO_FEW] and torch.isnan(res.pair_rms).all()
    assert torch.equal(res.T_wc, T) and res.disconnected.tolist() == [False, True, True] and res.converged
    empty = optimize(T[:1], torch.zeros(0, 2, dtype=torch.int64), PairStats.empty(0))
    assert torch.equal(empty.T_wc, T[:1]) and empty.converged
