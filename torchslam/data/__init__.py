"""Sequences and trajectories: TUM RGB-D reader, synthetic RGB-D-inertial generator, trajectory I/O."""

from .frame import Frame, Sequence, associate_timestamps
from .trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

__all__ = ["Frame", "Sequence", "Trajectory", "associate_timestamps", "read_tum_trajectory", "write_tum_trajectory"]
