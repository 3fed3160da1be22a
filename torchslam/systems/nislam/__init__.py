"""NI-SLAM: non-iterative RGB-D-inertial SLAM with kernel cross-correlators.

``config`` (settings), ``attitude`` (where rotations come from), ``policy`` (the keyframe /
fusion / lost rule), ``step`` (the per-frame phases the lockstep scheduler drives) and
``system`` (``NISlam``, one sequence). The tracking step itself is ``kcc.track_step``.
"""

from ...kcc import TrackResult, track_step
from ..base import StepReport
from .attitude import attitude_stream
from .config import AcceptanceCovariance, AttitudeSource, Gravity, LoopConfig, NISlamConfig
from .policy import KeyframePolicy
from .step import track_frames
from .system import SPEC, NISlam

__all__ = [
    "SPEC", "AcceptanceCovariance", "AttitudeSource", "Gravity", "KeyframePolicy", "LoopConfig", "NISlam", "NISlamConfig", "StepReport",
    "TrackResult", "attitude_stream", "track_frames", "track_step",
]
