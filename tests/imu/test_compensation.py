"""AccelerationCompensation: the attitude filter's tilt correction run again with the body's
acceleration removed from the accelerometer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data.synthetic.sequence import synthetic_kinematics
from torchslam.errors import ConfigError, ShapeError
from torchslam.geometry import so3_log
from torchslam.imu import ImuNoise, ahrs_attitude, attitude_errors, groundtruth_attitude, simulated_attitude
from torchslam.imu.attitude import _swing_to, quat_xyzw_to_rotmat
from torchslam.imu.compensation import AccelerationCompensation

F64 = torch.float64


def _sequence(noise: ImuNoise | None = None):
    """A translation-dominant synthetic sequence whose acceleration (about 2.5 m/s^2 rms) tilts
    the plain filter's attitude by about a degree."""
    cfg = SyntheticConfig(frames=150, trajectory="translate", seed=301, period=4.0, width=64, height=48,
                          imu_noise=noise if noise is not None else ImuNoise())
    return cfg, generate_sequence(cfg)


def _compensated(stream, times: torch.Tensor, positions: torch.Tensor, half_window: int = 5) -> torch.Tensor:
    """(N, 3, 3) attitudes at ``times`` with the compensation fed ``positions`` frame by frame,
    each frame's correction taken before its own position is observed (as NI-SLAM does)."""
    comp = AccelerationCompensation(stream, half_window)
    R, ok = stream.at(times)
    assert bool(ok.all())
    out = []
    for k in range(len(times)):
        out.append(comp.correction(float(times[k])) @ R[k])
        comp.observe(float(times[k]), positions[k])
    return torch.stack(out)


def test_filter_streams_keep_their_tilt_inputs_and_ground_truth_has_none():
    _, seq = _sequence()
    tilt = seq.attitude.tilt
    assert tilt is not None and tilt.specific_force.shape == (len(seq.imu), 3)
    # The kept low-pass output is the stream's: its swing onto +z times the gyro-only attitude is
    # the stream's attitude.
    R0 = seq.attitude.R_wc[0]
    gyro_only = ahrs_attitude(seq.imu, R0, time_constant=math.inf).R_wc
    for i in (1, len(seq.imu) // 2, len(seq.imu) - 1):
        u = tilt.up[i] / tilt.up[i].norm()
        expected = quat_xyzw_to_rotmat(_swing_to(u[None], torch.tensor([0.0, 0.0, 1.0], dtype=F64)))[0] @ gyro_only[i]
        assert torch.allclose(expected, seq.attitude.R_wc[i], atol=1e-9)
    assert groundtruth_attitude(seq.groundtruth).tilt is None
    with pytest.raises(ConfigError, match="no attitude filter"):
        AccelerationCompensation(groundtruth_attitude(seq.groundtruth))
    assert ahrs_attitude(seq.imu, time_constant=math.inf).tilt is None  # no tilt correction to redo


def test_zero_acceleration_reproduces_the_stream():
    """Positions that do not accelerate (a constant velocity) leave the filter's own inputs: the
    low-pass run again frame by frame reaches the stream's parallel-scan state, and the first
    frames, before a window is full, keep the stream's attitude."""
    _, seq = _sequence()
    t = seq.groundtruth.timestamps.to(F64)
    p = (t - t[0])[:, None] * torch.tensor([0.3, -0.1, 0.2], dtype=F64)
    R, _ = seq.attitude.at(t)
    comp = AccelerationCompensation(seq.attitude, 5)
    for k in range(len(t)):
        if k < 11:
            assert float((comp.correction(float(t[k])) @ R[k] - R[k]).abs().max()) < 1e-10
        comp.observe(float(t[k]), p[k])
    up = seq.attitude.tilt.up[comp._done].numpy()
    assert comp._done > 0 and comp.compensated_samples > 0
    np.testing.assert_allclose(comp._y.numpy(), up, rtol=0, atol=1e-9 * np.linalg.norm(up))


def test_true_positions_remove_the_tilt_the_acceleration_caused():
    """Planted: a noiseless IMU, so every tilt error of the plain filter is the body's own
    acceleration leaking into the gravity direction; fed the true positions, the compensation
    removes nearly all of it once the first window of 2 h + 1 = 11 frames is full (before, the
    samples go in uncorrected, as in the plain filter)."""
    _, seq = _sequence(ImuNoise.noiseless())
    gt = seq.groundtruth
    t = gt.timestamps.to(F64)
    R_plain, _ = seq.attitude.at(t)
    R_comp = _compensated(seq.attitude, t, gt.T_wc[:, :3, 3].to(F64))
    tilt_plain, _ = attitude_errors(R_plain, gt.T_wc[:, :3, :3].to(F64))
    tilt_comp, yaw_comp = attitude_errors(R_comp, gt.T_wc[:, :3, :3].to(F64))
    assert math.degrees(float(tilt_plain.max())) > 0.5  # the leak is there to remove
    assert torch.allclose(tilt_comp[:11], tilt_plain[:11], atol=1e-9)
    assert float(tilt_comp[11:].max()) < 0.1 * float(tilt_plain.max())
    assert math.degrees(float(yaw_comp.abs().max())) < 0.01  # a tilt correction never turns heading


def test_simulated_attitude_on_a_tilted_world_frame():
    """``simulated_attitude`` runs its filter in a z-up frame of its own: the compensation works
    through ``to_filter`` on a trajectory whose world has gravity along -y (a camera-style world)."""
    _, seq = _sequence(ImuNoise.noiseless())
    gt = seq.groundtruth
    # Rotate the world so that its up axis is +y (gravity along -y).
    W = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=F64)
    T = gt.T_wc.to(F64).clone()
    T[:, :3, :] = W @ T[:, :3, :]
    traj = type(gt)(gt.timestamps.to(F64), T)
    stream = simulated_attitude(traj, gyro_noise=0.0, bias_walk=0.0, gyro_bias_init=0.0, accel_noise=0.0,
                                accel_bias_walk=0.0, accel_bias_init=0.0, gravity_w=(0.0, -9.81, 0.0))
    assert stream.tilt is not None and torch.allclose(stream.tilt.to_filter @ torch.tensor([0.0, 1.0, 0.0], dtype=F64),
                                                      torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    t = traj.timestamps
    up = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    R_plain, _ = stream.at(t)
    R_comp = _compensated(stream, t, T[:, :3, 3])
    tilt_plain, _ = attitude_errors(R_plain, T[:, :3, :3], up=up)
    tilt_comp, _ = attitude_errors(R_comp, T[:, :3, :3], up=up)
    assert math.degrees(float(tilt_plain.max())) > 0.5
    assert float(tilt_comp[11:].max()) < 0.1 * float(tilt_plain.max())


def test_a_restart_holds_the_correction_and_a_step_back_in_time_restarts():
    cfg, seq = _sequence()
    gt = seq.groundtruth
    t = gt.timestamps.to(F64)
    p = gt.T_wc[:, :3, 3].to(F64)
    comp = AccelerationCompensation(seq.attitude, 2)
    for k in range(20):
        comp.observe(float(t[k]), p[k])
    done = comp.compensated_samples
    comp.restart()
    for k in range(20, 24):  # 4 positions: no window of 5 yet, nothing advances
        comp.observe(float(t[k]), p[k])
    assert comp.compensated_samples == done
    comp.observe(float(t[24]), p[24])
    assert comp.compensated_samples > done
    done = comp.compensated_samples
    comp.observe(float(t[10]), p[10])  # time went back: a new window starts
    assert comp.compensated_samples == done


def test_reposition_carries_the_window_through_a_moved_world():
    """A loop closure moves the world under the tracked frames. Planted: from frame 40 on the
    positions are seen 5 cm away (as a loop correction re-poses them). With the held window
    re-posed the same way the compensation goes on exactly as if nothing had moved (the fitted
    acceleration does not see a shift); a restart instead drops the compensation until a new
    window fills, and the acceleration's leak comes back meanwhile."""
    _, seq = _sequence(ImuNoise.noiseless())
    gt = seq.groundtruth
    t = gt.timestamps.to(F64)
    p = gt.T_wc[:, :3, 3].to(F64)
    moved = p + torch.tensor([0.05, -0.02, 0.01], dtype=F64)
    R, _ = seq.attitude.at(t)

    def run(at_40: str | None) -> torch.Tensor:
        comp = AccelerationCompensation(seq.attitude, 5)
        out = []
        for k in range(len(t)):
            if k == 40 and at_40 == "reposition":
                assert comp.held == 11
                comp.reposition(moved[40 - comp.held : 40])
            elif k == 40 and at_40 == "restart":
                comp.restart()
            out.append(comp.correction(float(t[k])) @ R[k])
            comp.observe(float(t[k]), (moved if at_40 is not None and k >= 40 else p)[k])
        return torch.stack(out)

    unmoved, repositioned, restarted = run(None), run("reposition"), run("restart")
    gap = so3_log(unmoved.transpose(-1, -2) @ repositioned).norm(dim=-1)
    assert math.degrees(float(gap.max())) < 1e-6
    tilt, _ = attitude_errors(unmoved, gt.T_wc[:, :3, :3].to(F64))
    tilt_restart, _ = attitude_errors(restarted, gt.T_wc[:, :3, :3].to(F64))
    assert float(tilt_restart[40:52].max()) > 3 * float(tilt[40:52].max())
    comp = AccelerationCompensation(seq.attitude, 5)
    comp.observe(float(t[0]), p[0])
    with pytest.raises(ShapeError, match="positions"):
        comp.reposition(p[:2])


def test_bad_half_window_is_refused():
    _, seq = _sequence()
    with pytest.raises(ConfigError, match="half_window"):
        AccelerationCompensation(seq.attitude, 1)


def test_synthetic_kinematics_accelerations_are_what_the_fit_sees():
    """The fit's acceleration on the true positions matches the true acceleration (an independent
    check of the 2 c term), away from the sequence ends."""
    cfg, seq = _sequence(ImuNoise.noiseless())
    gt = seq.groundtruth
    t = gt.timestamps.to(F64)
    kin = synthetic_kinematics(cfg, t)
    p = gt.T_wc[:, :3, 3].to(F64).numpy()
    tt = t.numpy()
    for j in (40, 75, 110):
        tau = tt[j - 5 : j + 6] - tt[j]
        A = np.stack([np.ones_like(tau), tau, tau * tau], 1)
        c, *_ = np.linalg.lstsq(A, p[j - 5 : j + 6], rcond=None)
        np.testing.assert_allclose(2 * c[2], kin.accel_w[j].numpy(), atol=0.05 * float(kin.accel_w[j].norm()) + 0.02)
