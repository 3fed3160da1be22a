"""IMU simulation and attitude streams: integration, noise model, AHRS behaviour, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data import Trajectory, read_tum_trajectory
from torchslam.errors import ConfigError, InvalidValueError, ShapeError
from torchslam.geometry import se3_from_Rt, so3_exp, so3_log
from torchslam.imu import (
    AttitudeStream,
    ImuData,
    ImuNoise,
    Kinematics,
    ahrs_attitude,
    attitude_errors,
    groundtruth_attitude,
    integrate_gyro,
    interpolate_rotations,
    kinematics_from_trajectory,
    make_generator,
    simulate_imu,
    simulated_attitude,
    start_up,
)

F64 = torch.float64
G_W = (0.0, 0.0, -9.81)



def _rz(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([c, -s, o, s, c, o, o, o, i], -1).reshape(a.shape + (3, 3))


def _rx(b: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(b), torch.sin(b), torch.zeros_like(b), torch.ones_like(b)
    return torch.stack([i, o, o, o, c, -s, o, s, c], -1).reshape(b.shape + (3, 3))


def _analytic_motion(t: torch.Tensor) -> Kinematics:
    """R = Rz(alpha) Rx(beta) with hand-derived body rates, and p = (sin t, cos 2t, 0.1 t^2)."""
    alpha, alpha_dot = 0.7 * t + 0.3 * torch.sin(1.3 * t), 0.7 + 0.39 * torch.cos(1.3 * t)
    beta, beta_dot = 0.4 * torch.sin(2.1 * t), 0.84 * torch.cos(2.1 * t)
    R = _rz(alpha) @ _rx(beta)
    # omega_b = Rx(beta)^T (0, 0, alpha_dot) + (beta_dot, 0, 0).
    omega = torch.stack([beta_dot, torch.sin(beta) * alpha_dot, torch.cos(beta) * alpha_dot], -1)
    accel = torch.stack([-torch.sin(t), -4 * torch.cos(2 * t), torch.full_like(t, 0.2)], -1)
    return Kinematics(t, R, omega, accel)


def _angle(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    return so3_log(R_a.transpose(-1, -2) @ R_b).norm(dim=-1)


# ------------------------------------------------------------------ gyro integration


def test_integrate_gyro_constant_rate_is_exact():
    t = torch.arange(5000, dtype=F64) / 200
    w = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    R0 = so3_exp(torch.tensor([0.1, 0.2, -0.3], dtype=F64))
    R = integrate_gyro(t, w.expand(5000, 3), R0)
    assert _angle(R, R0 @ so3_exp(t[:, None] * w)).max() < 1e-11


def test_integrate_gyro_equals_sequential_product():
    g = torch.Generator().manual_seed(1)
    t = torch.cumsum(0.004 + 0.002 * torch.rand(300, generator=g, dtype=F64), 0)
    w = torch.randn(300, 3, generator=g, dtype=F64)
    R = integrate_gyro(t, w)
    ref = [torch.eye(3, dtype=F64)]
    for i in range(299):  # the O(M) sequential definition the scan must reproduce
        dt = t[i + 1] - t[i]
        phi = 0.5 * (w[i] + w[i + 1]) * dt + dt * dt / 12 * torch.linalg.cross(w[i], w[i + 1])
        ref.append(ref[-1] @ so3_exp(phi))
    assert _angle(R, torch.stack(ref)).max() < 1e-12


def test_noise_free_gyro_reproduces_true_attitude():
    errors = []
    for rate in (200.0, 100.0):
        t = torch.arange(int(20 * rate) + 1, dtype=F64) / rate
        kin = _analytic_motion(t)
        imu = simulate_imu(kin, ImuNoise.noiseless(), G_W, 0).imu
        R = integrate_gyro(t, imu.gyro, kin.R_wb[0])
        errors.append(_angle(R, kin.R_wb).max())
    # 20 s of rotation at up to 1 rad/s: 200 Hz stays within 2e-5 rad.
    assert errors[0] < 2e-5
    # Third-order increments accumulate a second-order error: halving the rate quadruples it.
    assert 3.5 < errors[1] / errors[0] < 4.5


# ------------------------------------------------------------------ IMU simulation


def test_noise_free_accel_is_specific_force():
    t = torch.arange(401, dtype=F64) / 200
    kin = _analytic_motion(t)
    imu = simulate_imu(kin, ImuNoise.noiseless(), G_W, 0).imu
    # Independent check: finite differences of the analytic position and R^T (a - g).
    h = 1e-3

    def pos(x):
        return torch.stack([torch.sin(x), torch.cos(2 * x), 0.1 * x * x], -1)

    a_fd = (pos(t + h) - 2 * pos(t) + pos(t - h)) / (h * h)
    expected = (kin.R_wb.transpose(-1, -2) @ (a_fd - torch.tensor(G_W, dtype=F64))[:, :, None])[:, :, 0]
    assert (imu.accel - expected).abs().max() < 1e-5
    assert torch.equal(imu.gyro, kin.omega_b)


def test_imu_at_rest_measures_up_and_zero_rate():
    t = torch.arange(100, dtype=F64) / 200
    R = so3_exp(torch.tensor([0.4, -0.3, 1.0], dtype=F64)).expand(100, 3, 3)
    kin = Kinematics(t, R, torch.zeros(100, 3, dtype=F64), torch.zeros(100, 3, dtype=F64))
    imu = simulate_imu(kin, ImuNoise.noiseless(), G_W, 0).imu
    up_b = R[0].T @ torch.tensor([0.0, 0.0, 9.81], dtype=F64)
    assert torch.allclose(imu.accel, up_b.expand(100, 3), atol=1e-12)
    assert imu.gyro.abs().max() == 0


def _still(m: int, rate: float = 200.0) -> Kinematics:
    t = torch.arange(m, dtype=F64) / rate
    return Kinematics(t, torch.eye(3, dtype=F64).expand(m, 3, 3), torch.zeros(m, 3, dtype=F64), torch.zeros(m, 3, dtype=F64))


def test_white_noise_and_bias_walk_statistics():
    kin = _still(40000)
    white = ImuNoise(gyro_noise_density=1e-3, accel_noise_density=2e-2, gyro_bias_walk=0, accel_bias_walk=0, gyro_bias_init=0, accel_bias_init=0)
    imu = simulate_imu(kin, white, G_W, 3).imu
    # Per-sample standard deviation = density * sqrt(rate).
    assert imu.gyro.std(0) / (1e-3 * math.sqrt(200)) == pytest.approx(torch.ones(3, dtype=F64), rel=0.03)
    assert (imu.accel - imu.accel.mean(0)).std(0) / (2e-2 * math.sqrt(200)) == pytest.approx(torch.ones(3, dtype=F64), rel=0.03)
    walk = ImuNoise(gyro_noise_density=0, accel_noise_density=0, gyro_bias_walk=1e-3, accel_bias_walk=5e-3, gyro_bias_init=0, accel_bias_init=0)
    sim = simulate_imu(kin, walk, G_W, 4)
    # Bias steps have standard deviation walk * sqrt(dt); the bias starts at zero.
    assert torch.diff(sim.gyro_bias, dim=0).std(0) / (1e-3 * math.sqrt(1 / 200)) == pytest.approx(torch.ones(3, dtype=F64), rel=0.03)
    assert torch.diff(sim.accel_bias, dim=0).std(0) / (5e-3 * math.sqrt(1 / 200)) == pytest.approx(torch.ones(3, dtype=F64), rel=0.03)
    assert sim.gyro_bias[0].abs().max() == 0
    assert torch.allclose(sim.imu.gyro, sim.gyro_bias)


def test_simulation_is_deterministic_with_seed():
    kin = _analytic_motion(torch.arange(200, dtype=F64) / 200)
    a = simulate_imu(kin, ImuNoise(), G_W, 7).imu
    b = simulate_imu(kin, ImuNoise(), G_W, torch.Generator().manual_seed(7)).imu
    c = simulate_imu(kin, ImuNoise(), G_W, 8).imu
    assert torch.equal(a.gyro, b.gyro) and torch.equal(a.accel, b.accel)
    assert not torch.equal(a.gyro, c.gyro)


def test_kinematics_from_trajectory_recovers_rates_and_acceleration():
    # Poses at 30 Hz of a constant-rate rotation and a constant-acceleration translation.
    t = torch.arange(91, dtype=F64) / 30
    w = torch.tensor([0.2, -0.5, 0.3], dtype=F64)
    acc = torch.tensor([0.5, -0.2, 0.1], dtype=F64)
    T = se3_from_Rt(so3_exp(t[:, None] * w), 0.5 * t[:, None] ** 2 * acc + torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    kin = kinematics_from_trajectory(t, T, rate=200.0, accel_smoothing=0.05)
    assert kin.timestamps[0] == 0 and kin.timestamps[-1] == pytest.approx(3.0)
    assert torch.allclose(kin.omega_b, w.expand_as(kin.omega_b), atol=1e-10)
    R_ref, _ = interpolate_rotations(t, T[:, :3, :3], kin.timestamps)
    assert _angle(kin.R_wb, R_ref).max() < 1e-10
    # Gaussian smoothing keeps the second derivative of a parabola; edges (4 sigma) are padded.
    inner = (kin.timestamps > 0.25) & (kin.timestamps < 2.75)
    assert torch.allclose(kin.accel_w[inner], acc.expand(int(inner.sum()), 3), atol=2e-3)


# ------------------------------------------------------------------ attitude streams


def test_attitude_stream_slerp_and_validity():
    ts = torch.tensor([0.0, 1.0, 1.05, 2.0], dtype=F64)
    R = _rz(torch.tensor([0.0, 0.4, 0.5, 0.9], dtype=F64))
    stream = AttitudeStream(ts, R, "groundtruth")
    q = torch.tensor([0.5, 1.025, -0.1, 2.5, 1.5], dtype=F64)
    _, valid = stream.at(q, max_gap=0.6)
    assert valid.tolist() == [False, True, False, False, False]  # 0.5 and 1.5 lie in gaps > 0.6 s
    Ri, valid = stream.at(q, max_gap=1.0)
    assert valid.tolist() == [True, True, False, False, True]
    expected = torch.tensor([0.2, 0.45, 0.5 + 0.4 * 0.45 / 0.95], dtype=F64)
    assert _angle(Ri[[0, 1, 4]], _rz(expected)).max() < 1e-12
    assert _angle(Ri[2:4], torch.eye(3, dtype=F64).expand(2, 3, 3)).max() == 0


def test_attitude_stream_at_a_gap_of_exactly_max_gap_on_epoch_stamps():
    # A 10 Hz attitude stream at Unix-epoch stamps: its float64 gaps fall a few tenths of a
    # microsecond either side of 0.1 s; all are max_gap = 0.1 and interpolated across.
    ts = 1305031102.175304 + torch.arange(40, dtype=F64) * 0.1
    assert bool((ts.diff() > 0.1).any())
    stream = AttitudeStream(ts, _rz(torch.linspace(0, 1, 40, dtype=F64)), "groundtruth")
    _, valid = stream.at((ts[:-1] + ts[1:]) / 2, max_gap=0.1)
    assert bool(valid.all())
    _, valid = stream.at((ts[:-1] + ts[1:]) / 2, max_gap=0.1 - 1e-5)
    assert not bool(valid.any())


def test_groundtruth_attitude_is_the_trajectory():
    t = torch.arange(10, dtype=F64) / 10
    T = se3_from_Rt(so3_exp(torch.randn(10, 3, dtype=F64, generator=torch.Generator().manual_seed(0))), torch.zeros(10, 3, dtype=F64))
    stream = groundtruth_attitude(Trajectory(t, T))
    assert stream.source == "groundtruth"
    R, valid = stream.at(t)
    assert valid.all() and _angle(R, T[:, :3, :3]).max() < 1e-12


def test_attitude_errors_split_tilt_and_yaw():
    R_true = so3_exp(torch.tensor([[0.3, -0.2, 1.1]], dtype=F64))
    yaw_only = _rz(torch.tensor([0.3], dtype=F64)) @ R_true
    tilt, yaw = attitude_errors(yaw_only, R_true)
    assert tilt.abs().max() < 1e-12 and yaw[0] == pytest.approx(0.3, abs=1e-12)
    tilt_only = _rx(torch.tensor([-0.2], dtype=F64)) @ R_true
    tilt, yaw = attitude_errors(tilt_only, R_true)
    assert tilt[0] == pytest.approx(0.2, abs=1e-12) and yaw.abs().max() < 1e-12


def test_ahrs_initial_tilt_from_accelerometer():
    R = _rz(torch.tensor(0.8, dtype=F64)) @ _rx(torch.tensor(0.35, dtype=F64))
    kin = _still(200)
    kin = Kinematics(kin.timestamps, R.expand(200, 3, 3), kin.omega_b, kin.accel_w)
    imu = simulate_imu(kin, ImuNoise.noiseless(), G_W, 0).imu
    stream = ahrs_attitude(imu)
    tilt, yaw = attitude_errors(stream.R_wc, R.expand(200, 3, 3))
    assert stream.source == "imu"
    assert tilt.max() < 1e-9
    assert yaw[0] == pytest.approx(-0.8, abs=1e-9)  # yaw is unobservable and starts at zero


def _swinging(accel_x, seconds: float = 10.0, rate: float = 200.0):
    """A noiseless IMU on a tilted body pitching at 0.1 rad/s while its origin accelerates along
    world x by ``accel_x(t)``, and the true up in the body frame at the first sample."""
    t = torch.arange(int(seconds * rate) + 1, dtype=F64) / rate
    R = _rz(torch.tensor(0.8, dtype=F64)) @ _rx(-1.7 + 0.1 * t)
    omega = torch.tensor([0.1, 0.0, 0.0], dtype=F64).expand(len(t), 3)
    a = torch.zeros(len(t), 3, dtype=F64)
    a[:, 0] = accel_x(t)
    imu = simulate_imu(Kinematics(t, R, omega, a), ImuNoise.noiseless(), G_W, 0).imu
    return imu, R[0].T @ torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def _deg_between(u: torch.Tensor, v: torch.Tensor) -> float:
    return math.degrees(math.acos(min(1.0, float(u @ v / (u.norm() * v.norm())))))


def test_start_up_averages_the_motions_acceleration_out():
    # Swinging at 6 m/s^2 (period 2 s) from the swing's peak: the first 0.1 s of specific force
    # shows a tilt of about 31 degrees; ten seconds of whole swings cancel it, with the body
    # pitching by 57 degrees meanwhile (each sample turned back by the integrated gyro).
    imu, up = _swinging(lambda t: 6.0 * torch.cos(math.pi * t))
    assert _deg_between(start_up(imu, window=0.1), up) > 25.0
    assert _deg_between(start_up(imu), up) < 0.05
    # Without the gyro's turn the mean would be far off: the samples are not simply averaged.
    mean_f = imu.accel.mean(0)
    assert _deg_between(mean_f, up) > 10.0
    # The filter starts levelled by it (no ground-truth start given).
    R0 = ahrs_attitude(imu).R_wc[0]
    assert _deg_between(R0.T @ torch.tensor([0.0, 0.0, 1.0], dtype=F64), up) < 0.05


def test_start_up_is_off_by_the_spans_change_of_velocity():
    # 2 m/s^2 for the first second, then none: the mean specific force over the ten seconds is
    # gravity plus dv / T, so the level is off by atan(|dv| / (g T)), about 1.2 degrees.
    imu, up = _swinging(lambda t: torch.where(t <= 1.0, 2.0, 0.0).to(F64))
    n = len(imu.timestamps)
    mean_a = 2.0 * int((imu.timestamps <= 1.0).sum()) / n
    expected = math.degrees(math.atan2(mean_a, 9.81))
    assert _deg_between(start_up(imu), up) == pytest.approx(expected, abs=0.01)
    # A shorter window sees the first second only: the full 2 m/s^2 as a tilt.
    assert _deg_between(start_up(imu, window=0.5), up) == pytest.approx(math.degrees(math.atan2(2.0, 9.81)), abs=0.01)
    with pytest.raises(ConfigError, match="window"):
        start_up(imu, window=0.0)


def _long_motion(seconds: float = 60.0) -> Trajectory:
    """Poses at 30 Hz of a slowly panning, gently moving camera (|a| < 0.1 m/s^2)."""
    t = torch.arange(int(seconds * 30) + 1, dtype=F64) / 30
    R = _rz(0.5 * torch.sin(0.2 * t)) @ _rx(-1.7 + 0.1 * torch.sin(0.3 * t))
    p = torch.stack([0.5 * torch.sin(0.4 * t), 0.3 * torch.cos(0.5 * t), 1.0 + 0.1 * torch.sin(0.3 * t)], -1)
    return Trajectory(t, se3_from_Rt(R, p))


def test_simulated_attitude_yaw_drifts_with_bias_walk_and_tilt_stays_bounded():
    traj = _long_motion()
    common = dict(gyro_noise=1.7e-4, seed=5, gyro_bias_init=0.0, time_constant=2.0)
    small = simulated_attitude(traj, bias_walk=1e-5, **common)
    large = simulated_attitude(traj, bias_walk=5e-4, **common)
    gyro_only = simulated_attitude(traj, bias_walk=5e-4, **{**common, "time_constant": math.inf})
    assert small.source == "simulated"
    errs = {}
    for name, stream in (("small", small), ("large", large), ("gyro", gyro_only)):
        R, valid = stream.at(traj.timestamps)
        assert valid.all()
        errs[name] = attitude_errors(R, traj.T_wc[:, :3, :3])
    yaw_rms = {k: v[1].pow(2).mean().sqrt() for k, v in errs.items()}
    tilt_max = {k: v[0].max() for k, v in errs.items()}
    assert yaw_rms["large"] > 5 * yaw_rms["small"]
    # The accelerometer bounds roll and pitch; without it the same gyroscope tilts away.
    assert tilt_max["large"] < math.radians(1.5)
    assert tilt_max["gyro"] > 5 * tilt_max["large"]
    assert errs["large"][1].abs().max() > 2 * tilt_max["large"]  # heading drifts further than tilt


def test_simulated_attitude_on_tum_ground_truth(shared_data):
    traj = read_tum_trajectory(shared_data / "tum_fr1_xyz" / "groundtruth.txt")
    stream = simulated_attitude(traj, seed=0)
    R, valid = stream.at(traj.timestamps)
    assert stream.source == "simulated" and valid.all()
    tilt, yaw = attitude_errors(R, traj.T_wc[:, :3, :3])
    # A good MEMS unit over ~9 s: well under two degrees, yet not the ground truth.
    assert tilt.max() < math.radians(2) and yaw.abs().max() < math.radians(2)
    assert (tilt + yaw.abs()).max() > 1e-4
    gt = groundtruth_attitude(traj)
    Rg, valid = gt.at(traj.timestamps, max_gap=0.2)
    assert valid.all() and _angle(Rg, traj.T_wc[:, :3, :3]).max() < 1e-9


def test_noise_free_simulation_on_tum_reproduces_ground_truth(shared_data):
    # The C1 rotation curve through the motion-capture poses is what the gyroscope samples; with
    # every noise term zero, integration returns to the poses up to discretisation error.
    traj = read_tum_trajectory(shared_data / "tum_fr1_xyz" / "groundtruth.txt")
    zero = dict(gyro_noise=0.0, bias_walk=0.0, gyro_bias_init=0.0, accel_noise=0.0, accel_bias_walk=0.0, accel_bias_init=0.0)
    stream = simulated_attitude(traj, time_constant=math.inf, **zero)
    R, valid = stream.at(traj.timestamps)
    assert valid.all() and _angle(R, traj.T_wc[:, :3, :3]).max() < math.radians(0.2)


# ------------------------------------------------------------------ bad input


def test_bad_input_raises_named_errors():
    t = torch.arange(5, dtype=F64)
    with pytest.raises(ShapeError, match="gyro"):
        ImuData(t, torch.zeros(5, 3), torch.zeros(5, 3, dtype=F64))
    with pytest.raises(ShapeError, match="accel"):
        ImuData(t, torch.zeros(5, 3, dtype=F64), torch.zeros(4, 3, dtype=F64))
    with pytest.raises(InvalidValueError, match="strictly increasing"):
        ImuData(torch.tensor([0.0, 1.0, 1.0], dtype=F64), torch.zeros(3, 3, dtype=F64), torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ConfigError, match="gyro_bias_walk"):
        ImuNoise(gyro_bias_walk=-1.0)
    with pytest.raises(ConfigError, match="source"):
        AttitudeStream(t, torch.eye(3, dtype=F64).expand(5, 3, 3), "magic")
    imu = ImuData(t, torch.zeros(5, 3, dtype=F64), torch.tensor([0.0, 0.0, 9.81], dtype=F64).expand(5, 3).clone())
    with pytest.raises(ConfigError, match="time_constant"):
        ahrs_attitude(imu, time_constant=0.0)
    with pytest.raises(ShapeError, match="gyro"):
        integrate_gyro(t, torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ShapeError, match="timestamps"):
        kinematics_from_trajectory(t[:1], torch.eye(4, dtype=F64)[None])
    with pytest.raises(ConfigError, match="seed"):
        make_generator("seven")


def test_attitude_stream_with_cached_quaternions_equals_interpolate_rotations():
    from torchslam.geometry import so3_exp
    from torchslam.imu.attitude import AttitudeStream
    from torchslam.imu.simulate import interpolate_rotations

    g = torch.Generator().manual_seed(4)
    t = torch.cumsum(torch.rand(300, generator=g, dtype=torch.float64) * 0.02 + 0.001, 0)
    t[150:] += 0.3  # a gap wider than max_gap
    R = so3_exp(torch.randn(300, 3, generator=g, dtype=torch.float64))
    stream = AttitudeStream(t, R, "imu")
    # Inside, before, after, on samples, inside the gap.
    q = torch.cat([torch.rand(10, generator=g, dtype=torch.float64) * float(t[-1] + 1) - 0.5,
                   t[:1], t[-1:], t[149:150] + 0.1])
    for queries in (q, q[:2], q[-1:]):
        a, va = stream.at(queries, 0.1)  # cached quaternions
        b, vb = interpolate_rotations(t, R, queries, 0.1)
        assert torch.equal(va, vb) and torch.equal(a, b)
    assert not bool(stream.at(t[149:150] + 0.1, 0.1)[1][0])  # in the gap
    one = AttitudeStream(t[:1], R[:1], "imu")
    a, va = one.at(torch.tensor([float(t[0]), float(t[0]) + 1.0], dtype=torch.float64))
    b, vb = interpolate_rotations(t[:1], R[:1], torch.tensor([float(t[0]), float(t[0]) + 1.0], dtype=torch.float64))
    assert torch.equal(va, vb) and torch.equal(a, b)
