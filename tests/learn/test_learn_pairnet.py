"""FastGO pair weights from PairWeightNet: features, planted false loops, training through unrolled FastGO."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, ShapeError
from torchslam.fastgo import optimize
from torchslam.fastgo.synthetic import loop_route_problem
from torchslam.learn import (
    FEATURES,
    PairNetTrainConfig,
    PairWeightNet,
    evaluate_pairnet,
    false_loop_problem,
    pair_features,
    pose_error,
    train_pairnet,
    weighted_optimize,
)


def test_pair_features_against_raw_correspondences():
    P = loop_route_problem(10, lap_length=5, noise=0.02, correspondences=12, seed=4, keep_points=True)
    f = pair_features(P.T_init, P.pairs, P.stats)
    assert f.shape == (P.pairs.shape[0], len(FEATURES)) and f.dtype == torch.float64
    T = P.T_init.numpy()
    pi, pj, pairs = P.points_i.numpy(), P.points_j.numpy(), P.pairs.numpy()
    for m in (0, 7, pairs.shape[0] - 1):  # brute force per pair with NumPy
        i, j = pairs[m]
        qi = pi[m] @ T[i, :3, :3].T + T[i, :3, 3]
        qj = pj[m] @ T[j, :3, :3].T + T[j, :3, 3]
        rms = np.sqrt(((qi - qj) ** 2).sum(1).mean())
        ratios = []
        for p in (pi[m], pj[m]):
            ev = np.linalg.eigvalsh(np.cov(p.T, bias=True))
            ratios.append(ev[0] / ev[2])
        assert float(f[m, 0]) == pytest.approx(np.log(12))
        assert float(f[m, 1]) == pytest.approx(np.log(rms / 0.01 + 1e-6), rel=1e-8)
        assert float(f[m, 2]) == pytest.approx(np.log(min(ratios)), rel=1e-8)
        assert float(f[m, 3]) == pytest.approx(np.log1p(abs(i - j)))


def test_false_loop_problem_plants_pairs_that_disagree_with_the_truth():
    g = false_loop_problem(3, num_keyframes=16, num_false=4)
    assert int(g.false.sum()) == 4 and bool(g.false[-4:].all())
    assert g.pairs.shape[0] == len(g.stats) == g.false.shape[0]
    assert bool(((g.pairs[g.false, 1] - g.pairs[g.false, 0]) >= 3).all())
    # at the true poses the true pairs fit to noise level, the false ones by decimetres
    rms = pair_features(g.T_gt, g.pairs, g.stats)[:, 1].exp() * 0.01
    assert float(rms[~g.false].max()) < 0.03 and float(rms[g.false].min()) > 0.1
    with pytest.raises(ConfigError, match="num_keyframes"):
        false_loop_problem(0, num_keyframes=3)


def test_untrained_net_gives_weight_one_and_bounded_weights():
    net = PairWeightNet()
    x = torch.randn(9, len(FEATURES), dtype=torch.float64)
    assert torch.equal(net(x), torch.ones(9, dtype=torch.float64))
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 3.0)
    w = net(100 * x)
    assert bool((w > 0).all() and (w < 2).all())
    with pytest.raises(ShapeError, match="features"):
        net(torch.zeros(3, 5, dtype=torch.float64))
    with pytest.raises(ConfigError, match="hidden"):
        PairWeightNet(hidden=0)
    with pytest.raises(ConfigError, match="max_weight"):
        PairWeightNet(max_weight=0.0)


def test_unit_weights_equal_plain_fastgo_and_gradients_reach_the_net():
    g = false_loop_problem(5, num_keyframes=12, num_false=2)
    (T,) = weighted_optimize([g], None, 30, unrolled=False)
    ref = optimize(g.T_init, g.pairs, g.stats, iterations=30, tol=1e-10, step_tol=1e-12)
    assert torch.allclose(T, ref.T_wc, atol=1e-9)
    torch.manual_seed(0)
    net = PairWeightNet(hidden=4)
    torch.nn.init.normal_(net.mlp[-1].weight, std=0.1)
    (T,) = weighted_optimize([g], [net(pair_features(g.T_init, g.pairs, g.stats))], 3)
    pose_error(T, g.T_gt).backward()
    grads = [p.grad for p in net.parameters()]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in grads)
    assert sum(float(gr.abs().sum()) for gr in grads) > 0
    with pytest.raises(ShapeError, match="weights"):
        weighted_optimize([g], [], 3)


def test_pose_error_is_zero_at_the_truth_and_counts_rotation():
    g = false_loop_problem(1, num_keyframes=8, num_false=0)
    assert float(pose_error(g.T_gt, g.T_gt)) == 0.0
    T = g.T_gt.clone()
    T[:, 0, 3] += 0.1
    assert float(pose_error(T, g.T_gt)) == pytest.approx(0.01)
    with pytest.raises(ShapeError, match="T_gt"):
        pose_error(T, T[:3])


def test_training_lowers_false_pair_weights_and_pose_error():
    cfg = PairNetTrainConfig(train_seeds=(0, 1, 2, 3), val_seeds=(100, 101), num_keyframes=16, steps=25,
                             batch_size=0, eval_every=25, lr=0.02, hidden=8)
    res = train_pairnet(cfg)
    m = res.metrics
    assert m["train_loss_last"] < 0.2 * m["train_loss_first"]
    unit, learned = m["val_unit"], m["val_learned"]
    assert unit["weight_false"] == 1.0 and unit["rms_m"] > 0.03  # the false loops bend plain FastGO
    assert learned["weight_false"] < 0.2 and learned["weight_true"] > 0.8
    assert learned["rms_m"] < 0.5 * unit["rms_m"]  # held-out graphs
    # evaluate_pairnet with the returned net reproduces the reported figure
    again = evaluate_pairnet(res.module, [false_loop_problem(s, 16) for s in cfg.val_seeds], cfg.eval_iterations)
    assert again == pytest.approx(learned)


def test_train_config_validation():
    with pytest.raises(ConfigError, match="val_seeds: must not overlap"):
        PairNetTrainConfig(train_seeds=(1, 2), val_seeds=(2,))
    with pytest.raises(ConfigError, match="unroll"):
        PairNetTrainConfig(unroll=0)
    with pytest.raises(ConfigError, match="lr"):
        PairNetTrainConfig(lr=0.0)
