"""Loop-closure detection: MILD multi-index hashing over keyframe binary descriptors."""

from .mild import MILDConfig, MILDDatabase, MILDError, substring_keys

__all__ = ["MILDConfig", "MILDDatabase", "MILDError", "substring_keys"]
