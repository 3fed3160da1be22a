"""Trajectories: timestamps with camera-to-world poses, and TUM-format text I/O.

Convention:
    A TUM trajectory line is ``timestamp tx ty tz qx qy qz qw`` with the pose camera-to-world
    (``T_wc``) and the quaternion in xyzw order. Lines starting with ``#`` and blank lines are
    skipped.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..errors import DataFormatError, ShapeError, check_increasing, check_shape
from ..geometry import quat_xyzw_slerp, quat_xyzw_to_rotmat, rotmat_to_quat_xyzw, se3_from_Rt
from ..stamps import STAMP_TOLERANCE_S

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory"]


@dataclass(frozen=True)
class Trajectory:
    """A sequence of timestamped camera-to-world poses.

    Attributes:
        timestamps: (N,) float64 seconds, strictly increasing.
        T_wc: (N, 4, 4) float64 camera-to-world poses.
    """

    timestamps: Tensor
    T_wc: Tensor

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape(self.timestamps, "N", "timestamps", dims)
        check_shape(self.T_wc, "N 4 4", "T_wc", dims)
        if self.timestamps.dtype != torch.float64:
            raise ShapeError(f"timestamps: expected float64, got {self.timestamps.dtype}")
        check_increasing(self.timestamps, "timestamps")

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> Tensor:
        """(N, 3) camera centres in the world frame, metres."""
        return self.T_wc[:, :3, 3]

    @classmethod
    def from_tum_array(cls, data: Tensor) -> "Trajectory":
        """Build from an ``(N, 8)`` array of ``t tx ty tz qx qy qz qw`` rows."""
        check_shape(data, "N 8", "data")
        data = data.to(torch.float64)
        R = quat_xyzw_to_rotmat(data[:, 4:8])
        return cls(data[:, 0].contiguous(), se3_from_Rt(R, data[:, 1:4]))

    def to_tum_array(self) -> Tensor:
        """Return ``(N, 8)`` float64 rows ``t tx ty tz qx qy qz qw`` (``qw >= 0``)."""
        T = self.T_wc.to(torch.float64)
        q = rotmat_to_quat_xyzw(T[:, :3, :3])
        return torch.cat([self.timestamps.to(torch.float64)[:, None], T[:, :3, 3], q], dim=1)

    def slice(self, index) -> "Trajectory":
        """Return the poses selected by ``index`` (slice, bool mask or index tensor)."""
        return Trajectory(self.timestamps[index], self.T_wc[index])

    def interpolate(self, times: Tensor, max_gap: float = math.inf) -> tuple[Tensor, Tensor]:
        """Interpolate poses at ``times``: linear in translation, SLERP in rotation.

        Args:
            times: (M,) query timestamps, seconds.
            max_gap: queries whose two bracketing poses are further apart than this (beyond the
                rounding of timestamps, ``STAMP_TOLERANCE_S``), or that lie outside the
                trajectory's time span, are reported invalid.

        Returns:
            T_wc: (M, 4, 4) float64 interpolated poses (identity where invalid).
            valid: (M,) bool.
        """
        check_shape(times, "M", "times")
        if times.dtype != torch.float64:
            # float32 cannot hold Unix-epoch timestamps to better than ~100 s.
            raise ShapeError(f"times: expected float64 timestamps, got {times.dtype}")
        t = self.timestamps
        if len(self) == 0:
            M = times.shape[0]
            return torch.eye(4, dtype=torch.float64).expand(M, 4, 4).clone(), torch.zeros(M, dtype=torch.bool)
        hi = torch.searchsorted(t, times).clamp(1, max(len(self) - 1, 1))
        lo = hi - 1
        if len(self) == 1:
            hi = lo = torch.zeros_like(hi)
        t0, t1 = t[lo], t[hi]
        span = (t1 - t0)
        alpha = torch.where(span > 0, (times - t0) / torch.where(span > 0, span, torch.ones_like(span)), torch.zeros_like(span))
        inside = (times >= t[0]) & (times <= t[-1])
        valid = inside & (span <= max_gap + STAMP_TOLERANCE_S)
        q = rotmat_to_quat_xyzw(self.T_wc[:, :3, :3].to(torch.float64))
        qi = quat_xyzw_slerp(q[lo], q[hi], alpha)
        p = self.positions.to(torch.float64)
        pi = p[lo] + alpha[:, None] * (p[hi] - p[lo])
        T = se3_from_Rt(quat_xyzw_to_rotmat(qi), pi)
        T = torch.where(valid[:, None, None], T, torch.eye(4, dtype=torch.float64))
        return T, valid


def read_tum_trajectory(path: str | os.PathLike) -> Trajectory:
    """Read a TUM-format trajectory file.

    Raises:
        DataFormatError: naming the file and line for a malformed row, non-finite values, a
            zero quaternion, or timestamps that do not strictly increase.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DataFormatError(f"{path}: cannot read trajectory ({exc.strerror or exc})") from exc
    rows: list[list[float]] = []
    prev_t, prev_line = -math.inf, 0
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DataFormatError(f"{path}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            vals = [float(v) for v in parts]
        except ValueError as exc:
            raise DataFormatError(f"{path}:{lineno}: not a number ({exc})") from exc
        if not all(math.isfinite(v) for v in vals):
            raise DataFormatError(f"{path}:{lineno}: NaN or infinite value")
        if sum(v * v for v in vals[4:]) < 1e-12:
            raise DataFormatError(f"{path}:{lineno}: zero quaternion")
        if vals[0] <= prev_t:
            kind = "duplicate" if vals[0] == prev_t else "decreasing"
            raise DataFormatError(f"{path}:{lineno}: {kind} timestamp {parts[0]} (line {prev_line} has {prev_t!r})")
        prev_t, prev_line = vals[0], lineno
        rows.append(vals)
    if not rows:
        return Trajectory(torch.zeros(0, dtype=torch.float64), torch.zeros(0, 4, 4, dtype=torch.float64))
    return Trajectory.from_tum_array(torch.tensor(rows, dtype=torch.float64))


def write_tum_trajectory(path: str | os.PathLike, trajectory: Trajectory, header: str | None = None) -> None:
    """Write a trajectory as TUM text: ``timestamp tx ty tz qx qy qz qw`` per line."""
    path = Path(path)
    rows = trajectory.to_tum_array().tolist()
    lines = [] if header is None else [f"# {h}" for h in header.splitlines()]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    lines += [f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) for r in rows]
    path.write_text("\n".join(lines) + "\n")
