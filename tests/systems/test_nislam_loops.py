"""NI-SLAM's loop acceptance: planted true and false loops, at the pose graph and end to end."""

import math

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.geometry import se3_exp, se3_inverse
from torchslam.systems.nislam import LoopConfig, NISlam, NISlamConfig
from torchslam.systems.nislam.system import _Keyframe

from tests._helpers import run_with_ate, seeded

SMALL = dict(width=320, height=240)


def _planted_chain(attitude: str, loop: dict, n: int = 40, seed: int = 2):
    """A started NI-SLAM whose graph is a drifting chain of ``n`` keyframes 0.5 s apart.

    The odometry errors are drawn from each edge's covariance: 3 mm per axis, except one weak
    edge halfway (8 cm across the image plane: a weak correlation peak, as on a textureless
    wall), where the drift concentrates; the rotations' from the system's attitude model.
    Returns the system and the true keyframe poses (n, 4, 4).
    """
    seq = generate_sequence(SyntheticConfig(frames=3, trajectory="loop", **SMALL))
    system = NISlam(config_from_dict(NISlamConfig, {"attitude": attitude, "loop": loop}))
    system.start(seq)
    g = seeded(seed)
    th = torch.linspace(0, 2 * math.pi * (n - 1) / n, n, dtype=torch.float64)
    xi = torch.zeros(n, 6, dtype=torch.float64)
    xi[:, 0], xi[:, 1], xi[:, 5] = 1.5 * torch.cos(th), 1.1 * torch.sin(th), th
    T_gt = se3_exp(xi)
    sigma_r = math.sqrt(system._rotation_variance(0.5))
    T_est = [T_gt[0]]
    for k in range(1, n):
        sigma_t = [0.08, 0.08, 0.003] if k == n // 2 else [0.003] * 3
        sigma = torch.tensor(sigma_t + [sigma_r] * 3, dtype=torch.float64)
        T_meas = se3_inverse(T_gt[k - 1]) @ T_gt[k] @ se3_exp(sigma * torch.randn(6, generator=g, dtype=torch.float64))
        T_est.append(T_est[-1] @ T_meas)
        system._add_edge(k - 1, k, T_meas, torch.diag(sigma**-2))
    for k, T in enumerate(T_est):
        system.keyframes.append(_Keyframe(k, 0.5 * k, T, T[:3, :3].clone(), torch.ones(1), None, None, None))
    return system, T_gt


@pytest.mark.parametrize("attitude", ["groundtruth", "simulated"])
def test_true_loop_accepted_where_the_bend_rule_rejected_it(attitude):
    system, T_gt = _planted_chain(attitude, {})
    n = len(T_gt)
    drift = float((system.keyframes[-1].T_wk[:3, 3] - T_gt[-1, :3, 3]).norm())
    assert drift > 0.05  # larger than the old bend threshold
    T_loop = se3_inverse(T_gt[0]) @ T_gt[-1]
    sharp = torch.tensor([1e-4, 1e-4, 4e-5], dtype=torch.float64)
    # The same loop under the old rule (a 5 cm bend guard): the weak edges absorb the correction.
    old, _ = _planted_chain(attitude, {"max_odometry_bend_m": 0.05})
    assert not old._try_loop(0, n - 1, T_loop, sharp) and old.loops["rejected_by_odometry"] == 1
    assert system._try_loop(0, n - 1, T_loop, sharp)
    assert system.loops["accepted"] == 1 and system.loops["rejected_by_chi2"] == 0
    after = float((system.keyframes[-1].T_wk[:3, 3] - T_gt[-1, :3, 3]).norm())
    assert after < 0.2 * drift
    test = system.loop_tests[-1]
    assert test["chi2_increase"] <= test["threshold"]


@pytest.mark.parametrize("attitude", ["groundtruth", "simulated"])
@pytest.mark.parametrize("kind", ["offset", "elsewhere"])
def test_false_loop_rejected_and_rolled_back(attitude, kind):
    system, T_gt = _planted_chain(attitude, {})
    n = len(T_gt)
    T_loop = se3_inverse(T_gt[0]) @ T_gt[-1]
    j = 0
    if kind == "offset":
        T_loop = T_loop.clone()
        T_loop[:3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)
    else:
        j = n // 2  # the right measurement attached to a place half the loop away
    edges = len(system.edges_i)
    poses = torch.stack([kf.T_wk for kf in system.keyframes])
    assert not system._try_loop(j, n - 1, T_loop, torch.tensor([1e-4, 1e-4, 4e-5], dtype=torch.float64))
    assert system.loops["rejected_by_chi2"] == 1 and system.loops["accepted"] == 0
    assert len(system.edges_i) == edges
    assert torch.equal(torch.stack([kf.T_wk for kf in system.keyframes]), poses)


def test_rotation_variance_per_attitude_source():
    gt, _ = _planted_chain("groundtruth", {}, n=3)
    sim, _ = _planted_chain("simulated", {}, n=3)
    lc = LoopConfig()
    assert gt._rotation_variance(5.0) == pytest.approx(math.radians(lc.groundtruth_rotation_sigma_deg) ** 2)
    # Inertial attitude: the per-edge error plus the gyro drift, growing with the time between keyframes.
    assert sim._rotation_variance(0.0) == pytest.approx(math.radians(lc.rotation_sigma_deg) ** 2)
    assert sim._rotation_variance(0.5) < sim._rotation_variance(2.0) < sim._rotation_variance(8.0)
    c = sim.cfg
    dt = 2.0
    expected = math.radians(lc.rotation_sigma_deg) ** 2 + (lc.gyro_bias_sigma * dt) ** 2 + c.sim_gyro_noise**2 * dt + c.sim_bias_walk**2 * dt**3 / 3
    assert sim._rotation_variance(dt) == pytest.approx(expected)


def test_loop_keys_are_validated():
    with pytest.raises(ConfigError, match="chi2_quantile"):
        LoopConfig(chi2_quantile=1.0)
    with pytest.raises(ConfigError, match="translation_variance_scale"):
        LoopConfig(translation_variance_scale=0.0)
    assert math.isinf(LoopConfig().max_odometry_bend_m)


class _Planting(NISlam):
    """NI-SLAM that tests a false copy of every verified loop before the real one: the verified
    transform attached to the keyframe half the sequence away (a different place)."""

    planted: list[bool]

    def _try_loop(self, j_old, k_new, T_jk, variance, window=None):
        self.planted = getattr(self, "planted", [])
        if window is None:
            self.planted.append(super()._try_loop((j_old + k_new) // 2, k_new, T_jk, variance))
        return super()._try_loop(j_old, k_new, T_jk, variance, window)


def test_synthetic_revisit_accepts_the_true_loop_rejects_the_planted_one():
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, period=9.0, **SMALL))  # a revisit before the end
    for attitude in ("groundtruth", "simulated"):
        system = _Planting(config_from_dict(NISlamConfig, {"attitude": attitude}))
        result, a_loop = run_with_ate(system, seq)  # the ATE drop itself: test_nislam's loop test
        loops = result.output.metrics["loops"]
        assert system.planted and not any(system.planted), attitude
        assert loops["rejected_by_chi2"] == len(system.planted)
        assert loops["accepted"] >= 1 and loops["rejected_by_odometry"] == 0
        assert a_loop.stats["rmse"] < 0.01


def test_local_window_edge_moves_only_the_window():
    system, T_gt = _planted_chain("groundtruth", {"local_window": 3})
    n = len(T_gt)
    before = torch.stack([kf.T_wk for kf in system.keyframes])
    lo = n - 5
    T_true = se3_inverse(T_gt[n - 3]) @ T_gt[n - 1]
    sharp = torch.tensor([1e-4, 1e-4, 4e-5], dtype=torch.float64)
    assert system._try_loop(n - 3, n - 1, T_true, sharp, window=lo)
    after = torch.stack([kf.T_wk for kf in system.keyframes])
    assert torch.equal(after[: lo + 1], before[: lo + 1])  # outside the window, and its held first keyframe
    assert not torch.allclose(after[lo + 1 :], before[lo + 1 :])
    assert system.local["accepted"] == 1 and system.loops["accepted"] == 0 and not system.loop_tests
    wrong = T_true.clone()
    wrong[:3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)
    assert not system._try_loop(n - 4, n - 1, wrong, sharp, window=lo)
    assert system.local["rejected_by_chi2"] == 1
