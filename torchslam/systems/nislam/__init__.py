"""NI-SLAM: non-iterative RGB-D-inertial SLAM with kernel cross-correlators (see ``system``)."""

from .system import SPEC, LoopConfig, NISlam, NISlamConfig, StepReport, TrackResult, attitude_stream, track_frames, track_step

__all__ = ["SPEC", "LoopConfig", "NISlam", "NISlamConfig", "StepReport", "TrackResult", "attitude_stream", "track_frames", "track_step"]
