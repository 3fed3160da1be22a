"""NI-SLAM's loop acceptance: planted true and false loops, at the pose graph and end to end."""

import math
from dataclasses import replace

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.geometry import se3_exp, se3_inverse, so3_exp, so3_log
from torchslam.systems.monitor import Monitor
from torchslam.systems.nislam import AcceptanceCovariance, LoopConfig, NISlam, NISlamConfig
from torchslam.systems.nislam.system import _Keyframe

from tests._helpers import run_with_ate, seeded

SMALL = dict(width=320, height=240)


def _planted_chain(attitude: str, loop: dict, n: int = 40, seed: int = 2):
    """A started NI-SLAM whose graph is a drifting chain of ``n`` keyframes 0.5 s apart.

    The edges carry their true covariances, so the loop test takes them as they are
    (``acceptance_covariance`` "eq19" unless ``loop`` says otherwise).

    The odometry errors are drawn from each edge's covariance: 3 mm per axis, except one weak
    edge halfway (8 cm across the image plane: a weak correlation peak, as on a textureless
    wall), where the drift concentrates; the rotations' from the system's attitude model.
    Returns the system and the true keyframe poses (n, 4, 4).
    """
    seq = generate_sequence(SyntheticConfig(frames=3, trajectory="loop", **SMALL))
    system = NISlam(config_from_dict(NISlamConfig, {"attitude": attitude, "loop": {"acceptance_covariance": "eq19", **loop}}))
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
    # The drift stops growing at max_drift_deg (the attitude filter bounds it).
    cap = math.radians(lc.rotation_sigma_deg) ** 2 + math.radians(lc.max_drift_deg) ** 2
    assert sim._rotation_variance(60.0) == pytest.approx(cap) and sim._rotation_variance(600.0) == pytest.approx(cap)


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

    def _try_loop(self, j_old, k_new, T_jk, variance, window=None, rotation_cov=None):
        self.planted = getattr(self, "planted", [])
        if window is None:
            self.planted.append(super()._try_loop((j_old + k_new) // 2, k_new, T_jk, variance, rotation_cov=rotation_cov))
        return super()._try_loop(j_old, k_new, T_jk, variance, window, rotation_cov)


class _Recorder(Monitor):
    def __init__(self) -> None:
        self.values: dict[str, list[float]] = {}

    def scalar(self, tag, value, step) -> None:
        self.values.setdefault(tag, []).append(value)


def test_synthetic_revisit_accepts_the_true_loop_rejects_the_planted_one():
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, period=9.0, **SMALL))  # a revisit before the end
    for attitude in ("groundtruth", "simulated"):
        monitor = _Recorder()
        system = _Planting(config_from_dict(NISlamConfig, {"attitude": attitude}), monitor=monitor)
        result, a_loop = run_with_ate(system, seq)  # the ATE drop itself: test_nislam's loop test
        loops = result.output.metrics["loops"]
        assert system.planted and not any(system.planted), attitude
        assert loops["rejected_by_chi2"] == len(system.planted)
        assert loops["accepted"] >= 1 and loops["rejected_by_odometry"] == 0
        assert a_loop.stats["rmse"] < 0.01
        # Every loop trial logs its chi-square increase over the threshold (above 1: rejected).
        ratios = monitor.values["optimization/loop_chi2"]
        tests = result.output.metrics["loop_tests"]
        assert len(ratios) == len(tests) >= 2  # the planted loop and the true one
        assert ratios == pytest.approx([t["chi2_increase"] / t["threshold"] for t in tests])
        assert sum(r > 1 for r in ratios) == loops["rejected_by_chi2"] >= 1


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


def _frame(index: int, dt: float = 1 / 30):
    from types import SimpleNamespace

    return SimpleNamespace(index=index, timestamp=index * dt, geometry_time=index * dt)


def test_jitter_variance_recovers_planted_position_noise():
    """The odometry variance from the frames' jitter: a planted white noise on a smooth path."""
    system, _ = _planted_chain("simulated", {}, n=3)
    g = seeded(5)
    sigma = torch.tensor([0.001, 0.002, 0.0005], dtype=torch.float64)
    log = system.frames
    for m in range(40):  # an earlier keyframe's frames, far noisier: not counted
        log.record(_frame(m), 0, se3_exp(torch.cat([0.05 * torch.randn(3, generator=g, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)])))
    n = 600
    t = torch.arange(n, dtype=torch.float64) / 30
    path = torch.stack([0.1 * t, 0.02 * t**2, -0.05 * t], dim=1)  # 0.04 m/s^2: 0.04 mm per second difference
    for m in range(n):
        xi = torch.cat([path[m] + sigma * torch.randn(3, generator=g, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)])
        log.record(_frame(40 + m), 1, se3_exp(xi))
        if m == n // 2:  # a motion prior far off the path: not a measurement
            log.record(_frame(40 + m), 1, se3_exp(torch.tensor([5.0, 5.0, 5.0, 0.0, 0.0, 0.0], dtype=torch.float64)), "velocity")
    var = system._jitter_variance(1)
    assert torch.allclose(var, system.cfg.loop.jitter_variance_scale * sigma**2, rtol=0.25)
    # Too few frames: no estimate (the edge falls back to Eq. (19)).
    for m in range(system.cfg.loop.min_jitter_frames - 1):
        log.record(_frame(1000 + m), 2, se3_exp(torch.zeros(6, dtype=torch.float64)))
    assert system._jitter_variance(2) is None


def test_information_takes_a_calibrated_variance_unscaled():
    system, _ = _planted_chain("groundtruth", {"translation_variance_scale": 4.0, "depth_variance_scale": 9.0}, n=3)
    var = torch.tensor([1e-4, 4e-4, 9e-6], dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    scaled = torch.diagonal(system._information(eye, var, 0.5, 0.0, loop=False))[:3]
    raw = torch.diagonal(system._information(eye, var, 0.5, 0.0, loop=False, scaled=False))[:3]
    assert torch.allclose(raw, 1.0 / var)
    assert torch.allclose(scaled, 1.0 / (var * torch.tensor([4.0, 4.0, 9.0], dtype=torch.float64)))


@pytest.mark.parametrize("attitude", ["groundtruth", "simulated"])
def test_information_adds_the_attitude_shift_at_the_scene_depth(attitude):
    """The attitude's error over the edge's span shifts the image-plane content by depth x angle."""
    system, _ = _planted_chain(attitude, {}, n=3)
    var = torch.tensor([1e-4, 4e-4, 9e-6], dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    for span, loop in ((0.5, False), (40.0, True)):
        info = torch.diagonal(system._information(eye, var, span, 2.5, loop=loop, scaled=False))[:3]
        shift = 2.5**2 * system._rotation_variance(span)
        assert torch.allclose(1.0 / info, var + torch.tensor([shift, shift, 0.0], dtype=torch.float64))
    # an inertial attitude drifts over a loop's span; ground truth does not
    assert (system._rotation_variance(40.0) > 10 * system._rotation_variance(0.5)) == (attitude == "simulated")


def test_jitter_acceptance_changes_the_test_not_the_optimisation():
    seq = generate_sequence(SyntheticConfig(frames=60, fps=10.0, trajectory="orbit", seed=1, **SMALL))
    runs = {}
    for source in ("eq19", "jitter"):
        system = NISlam(config_from_dict(NISlamConfig, {"attitude": "groundtruth", "loop": {"acceptance_covariance": source}}))
        result, _ = run_with_ate(system, seq)
        runs[source] = (system, result.output)
    (eq, out_eq), (jit, out_jit) = runs["eq19"], runs["jitter"]
    odometry = sum(not loop for loop in jit.edges_loop)
    assert odometry >= 2 and out_jit.metrics["odometry_variances"]["jitter"] >= 1
    assert out_eq.metrics["odometry_variances"] == {"jitter": 0, "eq19": odometry}
    assert sum(out_jit.metrics["odometry_variances"].values()) == odometry
    # the same graph to optimise; only the test's covariances differ
    assert torch.equal(torch.stack(eq.edges_info), torch.stack(jit.edges_info))
    assert torch.equal(torch.stack(eq.edges_test_info), torch.stack(eq.edges_info))
    assert not torch.allclose(torch.stack(jit.edges_test_info), torch.stack(jit.edges_info))
    assert torch.equal(out_eq.T_wc, out_jit.T_wc)


@pytest.mark.parametrize("attitude", ["groundtruth", "simulated"])
def test_jitter_acceptance_optimises_an_accepted_loop_with_the_papers_covariances(attitude):
    """The default test ("jitter") accepts the chain's true loop and rejects a 1 m offset and a
    different place; the accepted loop is optimised as under the paper's covariances."""
    eq, T_gt = _planted_chain(attitude, {})
    jit, _ = _planted_chain(attitude, {"acceptance_covariance": "jitter"})
    assert NISlamConfig().loop.acceptance_covariance is AcceptanceCovariance.JITTER  # the default
    n = len(T_gt)
    T_loop = se3_inverse(T_gt[0]) @ T_gt[-1]
    sharp = torch.tensor([1e-4, 1e-4, 4e-5], dtype=torch.float64)
    assert eq._try_loop(0, n - 1, T_loop, sharp) and jit._try_loop(0, n - 1, T_loop, sharp)
    # the loop's test information allows for the chain's common drift (1 % of its path)
    path = sum(float((jit.keyframes[k + 1].T_wk[:3, 3] - jit.keyframes[k].T_wk[:3, 3]).norm()) for k in range(n - 1))
    assert jit._drift_variance(0, n - 1) == pytest.approx((0.01 * path) ** 2, rel=0.05)
    assert 1.0 / float(jit.edges_test_info[-1][0, 0]) > 1.0 / float(jit.edges_info[-1][0, 0]) + 0.5 * (0.01 * path) ** 2
    assert torch.equal(jit.edges_info[-1], eq.edges_info[-1])
    poses = lambda s: torch.stack([kf.T_wk for kf in s.keyframes])  # noqa: E731
    assert torch.allclose(poses(jit), poses(eq), atol=1e-6)
    for j, offset in ((0, 1.0), (n // 2, 0.0)):
        wrong, _ = _planted_chain(attitude, {"acceptance_covariance": "jitter"})
        T = (se3_inverse(T_gt[0]) @ T_gt[-1]).clone()
        T[:3, 3] += torch.tensor([offset, 0.0, 0.0], dtype=torch.float64)
        assert not wrong._try_loop(j, n - 1, T, sharp) and wrong.loops["rejected_by_chi2"] == 1


def test_acceptance_covariance_keys_are_validated():
    with pytest.raises(ConfigError, match="acceptance_covariance"):
        LoopConfig(acceptance_covariance="widest")
    with pytest.raises(ConfigError, match="drift_per_metre"):
        LoopConfig(drift_per_metre=-0.01)
    with pytest.raises(ConfigError, match="min_jitter_frames"):
        LoopConfig(min_jitter_frames=2)
    with pytest.raises(ConfigError, match="jitter_variance_scale"):
        LoopConfig(jitter_variance_scale=0.0)


class _TurnedLoops(NISlam):
    """NI-SLAM whose verified loops carry a planted heading error (the gyro's drift at a revisit)."""

    TURN_DEG = 0.8

    def _verify(self, cand, kf, centred=False):
        edge = super()._verify(cand, kf, centred)
        if edge is None:
            return None
        T = edge.T_jk.clone()
        turn = torch.tensor([0.0, math.radians(self.TURN_DEG), 0.0], dtype=torch.float64)  # about the camera's vertical
        T[:3, :3] = so3_exp(turn) @ T[:3, :3]
        return replace(edge, T_jk=T)


def _loop_edge_rotation_errors(system, seq):
    T_gt = seq.groundtruth.T_wc[[kf.frame_index for kf in system.keyframes]].to(torch.float64)
    errs = []
    for i, j, T, loop in zip(system.edges_i, system.edges_j, system.edges_T, system.edges_loop):
        if loop:
            R_true = T_gt[i, :3, :3].T @ T_gt[j, :3, :3]
            errs.append(math.degrees(float(so3_log(T[:3, :3].T @ R_true).norm())))
    return errs


def test_visual_rotation_measures_a_loops_heading():
    # A planted 0.8 deg heading error on every verified loop: the attitude's rotation keeps it;
    # the refinement over the old keyframe's map measures the loop's rotation instead.
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, period=9.0, **SMALL))
    errors, metrics = {}, {}
    for visual in (False, True):
        system = _TurnedLoops(config_from_dict(NISlamConfig, {"attitude": "simulated", "loop": {"visual_rotation": visual}}))
        result, _ = run_with_ate(system, seq)
        metrics[visual] = result.output.metrics["loop_visual_rotation"]
        errors[visual] = _loop_edge_rotation_errors(system, seq)
    assert metrics[False] is None
    assert metrics[True]["refined"] >= 1 and metrics[True]["max_change_deg"] > 0.5, metrics[True]
    assert errors[False] and min(errors[False]) > 0.4, errors  # the planted turn and the attitude's own error
    assert errors[True] and max(errors[True]) < 0.3, errors


def test_visual_rotation_never_refines_ground_truth_attitude():
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, period=9.0, **SMALL))
    system = _TurnedLoops(config_from_dict(NISlamConfig, {"attitude": "groundtruth"}))
    result, _ = run_with_ate(system, seq)
    assert result.output.metrics["loop_visual_rotation"] is None
    assert result.output.metrics["loops"]["verified"] >= 1


def test_measured_loop_rotation_enters_the_information():
    system, T_gt = _planted_chain("simulated", {})
    n = len(T_gt)
    T_loop = se3_inverse(T_gt[0]) @ T_gt[n - 1]
    var = torch.tensor([1e-4, 1e-4, 4e-5], dtype=torch.float64)
    plain = system._information(T_loop, var, 20.0, 2.0, loop=True)
    cov = torch.diag(torch.tensor([1e-6, 2e-6, 3e-6], dtype=torch.float64))
    measured = system._information(T_loop, var, 20.0, 2.0, loop=True, rotation_cov=cov)
    assert torch.count_nonzero(plain[3:, 3:]) == 0
    torch.testing.assert_close(measured[3:, 3:], torch.linalg.inv(cov))
    # The attitude's share of the x, y variance now comes from the measured rotation: smaller.
    assert bool((measured[:2, :2].diagonal() > plain[:2, :2].diagonal()).all())
