"""Loop-closure acceptance (paper §IV-C): true loops kept, false loops rolled back."""

from __future__ import annotations

import torch

from torchslam.fastgo import FastGOProblem, PairStats, accept_loop_closures, accept_loop_closures_batch, optimize
from torchslam.fastgo.synthetic import loop_route_problem, make_correspondences
from torchslam.geometry import se3_exp, se3_inverse, se3_log


def pose_error(A, B) -> float:
    return float(se3_log(se3_inverse(A) @ B).abs().max())


def split_problem(seed: int):
    P = loop_route_problem(40, lap_length=20, loops_per_keyframe=1, local_pairs=2, noise=0.005, seed=seed)
    gap = (P.pairs[:, 1] - P.pairs[:, 0]).abs()
    odo = gap <= 3
    T_odo = optimize(P.T_init, P.pairs[odo], P.stats[odo]).T_wc  # consistent but drifted
    return P, odo, T_odo


def false_loop(P, seed: int):
    g = torch.Generator().manual_seed(seed)
    wrong = P.T_gt.clone()
    wrong[30] = se3_exp(torch.tensor([0.5, 0.4, -0.2, 0.1, -0.15, 0.2], dtype=torch.float64)) @ wrong[30]
    pairs = torch.tensor([[5, 30]])
    li, lj = make_correspondences(wrong, pairs, 32, 0.005, g)
    return pairs, PairStats.from_padded(li, lj)


def test_true_loops_are_accepted_and_remove_drift():
    P, odo, T_odo = split_problem(0)
    loops = ~odo
    dec = accept_loop_closures(T_odo, P.pairs[odo], P.stats[odo], P.pairs[loops], P.stats[loops])
    assert dec.accepted
    assert dec.cost_after <= 1.05 * dec.cost_before
    assert dec.pairs.shape[0] == P.pairs.shape[0] and len(dec.stats) == P.pairs.shape[0]
    assert pose_error(dec.T_wc, P.T_gt) < 0.7 * pose_error(T_odo, P.T_gt)


def test_false_loop_is_rejected_and_rolled_back():
    P, odo, T_odo = split_problem(1)
    lp, ls = false_loop(P, 1)
    dec = accept_loop_closures(T_odo, P.pairs[odo], P.stats[odo], lp, ls)
    assert not dec.accepted
    assert dec.cost_after > 1.05 * dec.cost_before
    assert torch.equal(dec.T_wc, T_odo)
    assert torch.equal(dec.pairs, P.pairs[odo]) and len(dec.stats) == int(odo.sum())
    # the trial really moved the map (that is what was measured and refused)
    assert pose_error(dec.result.T_wc, T_odo) > 0.01


def test_batched_decisions_are_independent():
    P0, odo0, T0 = split_problem(2)
    P1, odo1, T1 = split_problem(3)
    lp, ls = false_loop(P1, 3)
    problems = [FastGOProblem(T0, P0.pairs[odo0], P0.stats[odo0]), FastGOProblem(T1, P1.pairs[odo1], P1.stats[odo1])]
    decs = accept_loop_closures_batch(problems, [(P0.pairs[~odo0], P0.stats[~odo0]), (lp, ls)])
    assert [d.accepted for d in decs] == [True, False]
    single = accept_loop_closures(T0, P0.pairs[odo0], P0.stats[odo0], P0.pairs[~odo0], P0.stats[~odo0])
    assert pose_error(decs[0].T_wc, single.T_wc) < 1e-9
    assert torch.equal(decs[1].T_wc, T1)
