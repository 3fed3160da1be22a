"""GC-SLAM: sparse or dense registration with FastGO global optimisation.

``config`` holds the settings, ``frontend`` the sparse and dense front-ends, ``optimizer`` the
FastGO / loop-closure side and ``system`` the tracker (:class:`GCSlam`) and the lockstep steps.
"""

from .config import Frontend, GCSlamConfig
from .system import SPEC, GCSlam, insert_keyframe, insert_keyframes, track_frames

__all__ = ["SPEC", "Frontend", "GCSlam", "GCSlamConfig", "insert_keyframe", "insert_keyframes", "track_frames"]
