"""Timestamp comparisons shared by the data, IMU and system layers."""

from __future__ import annotations

__all__ = ["STAMP_TOLERANCE_S"]

# A gap compared against a limit (``max_gap``, ``motion_prior_max_gap``, ...) may exceed it by this
# much and still pass. Timestamps carry microseconds at best (TUM files write six decimals), and a
# difference of two Unix-epoch stamps in float64 is off by up to about 2.4e-7 s (the spacing of
# doubles near 1.3e9), so a stream sampled exactly every ``limit`` seconds has gaps a few tenths of
# a microsecond either side of it.
STAMP_TOLERANCE_S = 1e-6
