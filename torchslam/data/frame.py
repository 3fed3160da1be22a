"""The frame record every sequence yields, the interface sequences share, and timestamp association."""

from __future__ import annotations

from collections import abc
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError, check_shape
from ..geometry import PinholeCamera
from .trajectory import Trajectory

if TYPE_CHECKING:
    from ..imu.attitude import AttitudeStream

__all__ = ["Frame", "Sequence", "associate_timestamps"]


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame.

    Attributes:
        index: position of the frame in its sequence (after stride and range selection).
        timestamp: seconds (the colour image's timestamp).
        rgb: (3, H, W) float32 colour in [0, 1].
        depth: (1, H, W) float32 depth in metres, 0 = invalid.
        T_wc: (4, 4) float64 ground-truth camera-to-world pose, or None where there is none.
        depth_timestamp: seconds at which the depth image was taken, where it differs from the
            colour image's (TUM pairs colour and depth up to 20 ms apart); None when the
            sequence does not record it (then the depth is taken at ``timestamp``).
    """

    index: int
    timestamp: float
    rgb: Tensor
    depth: Tensor
    T_wc: Tensor | None = None
    depth_timestamp: float | None = None

    @property
    def geometry_time(self) -> float:
        """When the frame's geometry was observed: the depth image's timestamp where recorded.

        Both systems pose a frame at this instant (its 3-D points come from the depth image) and
        re-sample the trajectory at the colour ``timestamp`` at the end.
        """
        return self.timestamp if self.depth_timestamp is None else float(self.depth_timestamp)


@runtime_checkable
class Sequence(Protocol):
    """What a system needs from a sequence; ``TUMSequence`` and ``SyntheticSequence`` provide it.

    Required:
        name: the sequence's name (run folders, messages).
        camera: its intrinsics and image size.
        timestamps: (N,) float64 frame (colour image) times, seconds.
        groundtruth: the ground-truth pose of each frame that has one (a Trajectory over a
            subset of ``timestamps``), or None.

    Optional (a class that inherits from ``Sequence`` gets the defaults below; a class that
    implements the protocol without inheriting from it defines them itself):
        attitude: the sequence's own attitude stream (an AHRS on its IMU), or None (default)
            where it has no gyroscope. NI-SLAM's ``attitude=imu`` takes it.
        groundtruth_raw: the ground truth as its file holds it (its own stamps, not matched to
            frames), or None (default) where there is no such file. The headline ATE and
            NI-SLAM's ground-truth attitude are taken against it where present.
        skipped: ``(index, reason)`` of the frames the sequence could not decode and skipped
            during the last pass, in order; empty (default) for sequences that never skip.
        readout_time: the sensor's rolling-shutter readout, seconds from its first image row to
            its last, as far as the sequence knows it; 0 (default): a global shutter, or unknown.
            GC-SLAM's ``readout_time=auto`` takes it.
        readout_source: where ``readout_time`` came from, or None (default).
    """

    name: str
    camera: PinholeCamera
    timestamps: Tensor
    groundtruth: Trajectory | None
    attitude: AttitudeStream | None = None
    groundtruth_raw: Trajectory | None = None
    skipped: abc.Sequence[tuple[int, str]] = ()
    readout_time: float = 0.0
    readout_source: str | None = None

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...


def associate_timestamps(first: Tensor, second: Tensor, max_gap: float = 0.02) -> tuple[Tensor, Tensor]:
    """Match two timestamp lists one-to-one, closest pairs first, within ``max_gap`` seconds.

    This is the TUM RGB-D benchmark's association rule: every candidate pair closer than
    ``max_gap`` is considered in order of increasing gap and accepted when neither of its
    stamps is taken yet. Unlike a nearest-neighbour lookup, no stamp is used twice, so two
    colour frames never share one depth image.

    Args:
        first: (N,) float64 timestamps, seconds.
        second: (M,) float64 timestamps, seconds.
        max_gap: largest accepted |t_first - t_second|, seconds.

    Returns:
        idx_first, idx_second: (K,) int64 indices of matched pairs, sorted by ``idx_first``.
    """
    check_shape(first, "N", "first")
    check_shape(second, "M", "second")
    if max_gap < 0:
        raise ConfigError(f"max_gap: must be >= 0, got {max_gap}")
    a = first.detach().cpu().to(torch.float64).numpy()
    b = second.detach().cpu().to(torch.float64).numpy()
    if a.size == 0 or b.size == 0:
        empty = torch.zeros(0, dtype=torch.int64)
        return empty, empty.clone()
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_gap, side="left")
    hi = np.searchsorted(bs, a + max_gap, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(a.size), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ib_sorted = np.repeat(lo, counts) + offsets
    gaps = np.abs(a[ia] - bs[ib_sorted])
    keep = gaps <= max_gap
    ia, ib, gaps = ia[keep], order_b[ib_sorted[keep]], gaps[keep]
    used_a = np.zeros(a.size, dtype=bool)
    used_b = np.zeros(b.size, dtype=bool)
    out_a, out_b = [], []
    # Greedy over candidate pairs (a handful per stamp); this is I/O set-up, not a hot path.
    for k in np.lexsort((ib, ia, gaps)):
        i, j = ia[k], ib[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            out_a.append(i)
            out_b.append(j)
    order = np.argsort(np.asarray(out_a, dtype=np.int64), kind="stable")
    return (
        torch.as_tensor(np.asarray(out_a, dtype=np.int64)[order]),
        torch.as_tensor(np.asarray(out_b, dtype=np.int64)[order]),
    )
