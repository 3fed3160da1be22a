"""Sequences and trajectories: TUM RGB-D reader, synthetic RGB-D-inertial generator, trajectory I/O."""

from .trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory"]
