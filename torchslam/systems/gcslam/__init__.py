"""GC-SLAM: sparse or dense registration with FastGO global optimisation (see ``system``)."""

from .system import SPEC, GCSlam, GCSlamConfig, insert_keyframes, track_frames

__all__ = ["SPEC", "GCSlam", "GCSlamConfig", "insert_keyframes", "track_frames"]
