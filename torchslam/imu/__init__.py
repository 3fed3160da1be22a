"""IMU records, IMU simulation from ground truth, and attitude streams (ground truth, simulated, AHRS)."""

from .attitude import (
    ATTITUDE_SOURCES,
    LEVEL_WINDOW_S,
    AttitudeSource,
    AttitudeStream,
    ahrs_attitude,
    attitude_errors,
    groundtruth_attitude,
    integrate_gyro,
    simulated_attitude,
    start_up,
)
from .simulate import (
    GRAVITY_W,
    ImuData,
    ImuNoise,
    Kinematics,
    SimulatedImu,
    interpolate_rotations,
    kinematics_from_trajectory,
    make_generator,
    simulate_imu,
    time_derivatives,
)

__all__ = [
    "ATTITUDE_SOURCES",
    "AttitudeSource",
    "AttitudeStream",
    "GRAVITY_W",
    "ImuData",
    "ImuNoise",
    "Kinematics",
    "LEVEL_WINDOW_S",
    "SimulatedImu",
    "ahrs_attitude",
    "attitude_errors",
    "groundtruth_attitude",
    "integrate_gyro",
    "interpolate_rotations",
    "kinematics_from_trajectory",
    "make_generator",
    "simulate_imu",
    "simulated_attitude",
    "start_up",
    "time_derivatives",
]
