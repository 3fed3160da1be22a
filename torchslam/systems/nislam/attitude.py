"""Where NI-SLAM's rotations come from: the attitude source chosen for a sequence (``NISlamConfig.attitude``)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...data.frame import Sequence
from ...errors import ConfigError
from ...imu.attitude import AttitudeStream, groundtruth_attitude, simulated_attitude
from .config import AttitudeSource, Gravity, NISlamConfig

__all__ = ["attitude_stream", "gravity_vector"]

_AXES = {"x": 0, "y": 1, "z": 2}


def _nearest_axis(v: Tensor) -> Tensor:
    k = int(v.abs().argmax())
    out = torch.zeros(3, dtype=torch.float64)
    out[k] = 1.0 if float(v[k]) > 0 else -1.0
    return out


def gravity_vector(choice: Gravity, groundtruth) -> Tensor:
    """(3,) float64 world gravity, m/s^2, for the simulated attitude.

    ``Gravity.AUTO`` takes the world axis nearest the mean camera-down direction of the ground truth:
    camera y points down in the image, so its mean world direction is "down" for a camera held
    roughly upright, and datasets use axis-aligned worlds.
    """
    if choice is not Gravity.AUTO:
        sign = -1.0 if choice.value.startswith("-") else 1.0
        g = torch.zeros(3, dtype=torch.float64)
        g[_AXES[choice.value[-1]]] = 9.81 * sign
        return g
    down = groundtruth.T_wc[:, :3, 1].mean(0)
    return 9.81 * _nearest_axis(down)


def attitude_stream(sequence: Sequence, cfg: NISlamConfig) -> AttitudeStream:
    """Choose and build the attitude stream for ``sequence`` (see ``NISlamConfig.attitude``).

    Raises:
        ConfigError: the chosen source needs data the sequence does not have.
    """
    choice = cfg.attitude
    imu_stream = getattr(sequence, "attitude", None)
    gt = getattr(sequence, "groundtruth_raw", None)
    if gt is None:
        gt = sequence.groundtruth
    if choice is AttitudeSource.AUTO:
        choice = AttitudeSource.IMU if imu_stream is not None else AttitudeSource.SIMULATED
    if choice is AttitudeSource.IMU:
        if imu_stream is None:
            raise ConfigError(
                f"attitude=imu: {sequence.name} has no IMU stream (a TUM-layout folder needs an imu.txt; "
                "TUM RGB-D has no gyroscope); "
                "use attitude=simulated or attitude=groundtruth"
            )
        return imu_stream
    if gt is None or len(gt) < 2:
        raise ConfigError(f"attitude={choice.value}: {sequence.name} has no ground truth to derive the attitude from")
    if choice is AttitudeSource.GROUNDTRUTH:
        return groundtruth_attitude(gt)
    return simulated_attitude(
        gt, gyro_noise=cfg.sim_gyro_noise, bias_walk=cfg.sim_bias_walk, seed=cfg.sim_seed,
        gravity_w=gravity_vector(cfg.gravity, gt),
    )
