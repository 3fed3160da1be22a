"""Sequences and trajectories: TUM RGB-D reader, synthetic RGB-D-inertial generator, trajectory I/O."""

from .calibration import INTRINSICS_PRESETS, Calibration, CameraPreset, preset_for_name, read_calibration, resolve_calibration
from .frame import Frame, Sequence, associate_timestamps
from .synthetic import (
    SYNTHETIC_TRAJECTORIES,
    SyntheticConfig,
    SyntheticSequence,
    generate_sequence,
    write_tum_folder,
)
from .trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory
from .tum import AssociationStats, CorruptImageError, ImageFormatError, TUMSequence, sequence_info

__all__ = [
    "INTRINSICS_PRESETS",
    "AssociationStats",
    "Calibration",
    "CameraPreset",
    "CorruptImageError",
    "ImageFormatError",
    "Frame",
    "SYNTHETIC_TRAJECTORIES",
    "Sequence",
    "SyntheticConfig",
    "SyntheticSequence",
    "TUMSequence",
    "Trajectory",
    "associate_timestamps",
    "generate_sequence",
    "preset_for_name",
    "read_calibration",
    "read_tum_trajectory",
    "resolve_calibration",
    "sequence_info",
    "write_tum_trajectory",
    "write_tum_folder",
]
