"""Estimate the clock offset between an attitude stream and a camera from the images.

NI-SLAM takes every rotation from the attitude stream, so the stream must be sampled at the
instant the camera saw the scene. A constant offset ``delta`` between the two clocks turns into
an attitude error of about ``|omega| * delta`` at angular rate ``omega``, and an orthographic
image rotated by a wrong attitude is displaced by about ``depth * |omega| * delta``: on TUM
fr1/xyz (about 0.3 rad/s, 1.7 m) 20 ms is 1 cm, the size of the paper's whole ATE.

The estimate is the usual camera-IMU temporal calibration by rotation agreement:

1. ``P`` frame pairs ``(i, i + gap)`` spread over the sequence are registered densely
   (``registration.dense``, depth-dominated), giving the camera's relative rotations
   ``R_ij`` at the two frames' geometry (depth) instants.
2. For every candidate offset ``delta`` on a grid, the stream's relative rotation over the same
   pair, sampled at ``t + delta``, is compared with ``R_ij``; the cost is the RMS of the angles
   of ``R_ij^T R_stream,ij(delta)`` over the pairs that registered (angles clipped at
   ``clip_deg`` so that a failed registration cannot dominate), for all offsets at once.
3. The offset is the grid minimum refined by a parabola through it and its two neighbours.

Only rotations enter: no ground-truth position is used, so the estimate is as available for a
real IMU as for the ground-truth attitude stream of TUM. The camera-to-IMU rotation is taken
as known (the stream holds camera rotations).

Convention: the attitude for an image stamped ``t`` is the stream's sample at ``t + offset``
(``NISlamConfig.attitude_time_offset``).

The depth stream's latency against the colour stream (``data.depth_time_offset``: a depth image
was taken at its stamp plus it) needs no attitude stream: :func:`estimate_depth_time_offset`
compares the rotations of the two streams' own images.

1. Within a few windows of consecutive frames, each frame is registered to the next with the
   geometric term alone (``geometric_weight`` 1000: depth images); the chained rotations are a
   rotation stream at the depth images' instants.
2. Pairs ``(i, i + frame_gap)`` of the same windows are registered with the photometric term
   alone (``geometric_weight`` 0): rotations between the colour images' instants (the depth of
   the first frame only lifts its pixels, which a rotation barely depends on).
3. For every candidate latency ``d``, the depth stream's rotation over each pair, sampled at the
   colour stamps minus ``d``, is compared with the colour rotation as above; the minimum is
   refined by the same parabola.

A planted latency of a synthetic sequence (``SyntheticConfig.depth_time_offset``) is found to
within 3 ms (``tests/slam/test_depth_time_offset.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..data.frame import Sequence
from ..errors import ConfigError, TorchSlamError, check_shape
from ..geometry import so3_angle
from ..imu.attitude import AttitudeSource, AttitudeStream
from ..registration.dense import DenseConfig, register_dense

__all__ = ["TimeOffsetEstimate", "estimate_attitude_time_offset", "estimate_depth_time_offset", "rotation_agreement"]


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """Result of ``estimate_attitude_time_offset``.

    Attributes:
        offset: the estimated offset, seconds: sample the stream at ``image stamp + offset``.
        offsets: (K,) float64 candidate offsets, seconds.
        cost: (K,) float64 RMS rotation disagreement at each candidate, degrees.
        pairs: frame pairs that registered and entered the cost.
        cost_at_zero: RMS disagreement without an offset, degrees.
        cost_at_offset: RMS disagreement at ``offset``, degrees.
        at_edge: the minimum lies on the first or last candidate: the search range may be too
            narrow.
    """

    offset: float
    offsets: Tensor
    cost: Tensor
    pairs: int
    cost_at_zero: float
    cost_at_offset: float
    at_edge: bool

    def to_dict(self) -> dict:
        return {
            "offset_s": self.offset,
            "pairs": self.pairs,
            "cost_at_zero_deg": self.cost_at_zero,
            "cost_at_offset_deg": self.cost_at_offset,
            "at_edge": self.at_edge,
            "offsets_s": self.offsets.tolist(),
            "cost_deg": self.cost.tolist(),
        }


def rotation_agreement(
    stream: AttitudeStream,
    t_i: Tensor,
    t_j: Tensor,
    R_ij: Tensor,
    offsets: Tensor,
    max_gap: float = 0.1,
    clip_deg: float = 2.0,
) -> Tensor:
    """RMS angle between camera relative rotations and the stream's, for each candidate offset.

    Args:
        stream: camera-to-world attitude stream.
        t_i, t_j: (P,) float64 instants of the pairs' two frames, seconds (camera clock).
        R_ij: (P, 3, 3) measured rotations of frame j in frame i (``R_wi^T R_wj``).
        offsets: (K,) float64 candidate offsets, seconds.
        max_gap: stream gaps wider than this make a pair invalid at that offset.
        clip_deg: angles are clipped here before the RMS.

    Returns:
        (K,) float64 RMS angle in degrees over the pairs valid at each offset (inf where none).
    """
    dims: dict[str, int] = {}
    check_shape(t_i, "P", "t_i", dims)
    check_shape(t_j, "P", "t_j", dims)
    check_shape(R_ij, "P 3 3", "R_ij", dims)
    check_shape(offsets, "K", "offsets")
    K, P = offsets.shape[0], t_i.shape[0]
    times = torch.stack([t_i, t_j]).to(torch.float64)  # (2, P)
    q = (times[None] + offsets.to(torch.float64)[:, None, None]).reshape(-1)  # (K*2*P,)
    R, ok = stream.at(q, max_gap)
    R = R.view(K, 2, P, 3, 3)
    ok = ok.view(K, 2, P).all(dim=1)  # (K, P)
    S_ij = R[:, 0].transpose(-1, -2) @ R[:, 1]  # (K, P, 3, 3)
    ang = torch.rad2deg(so3_angle(R_ij.to(torch.float64).transpose(-1, -2)[None] @ S_ij)).clamp(max=clip_deg)
    n = ok.sum(-1)
    ms = (ang.square() * ok).sum(-1) / n.clamp_min(1)
    return torch.where(n > 0, ms.sqrt(), torch.full_like(ms, math.inf))


def _parabola_min(x: Tensor, y: Tensor, k: int) -> float:
    """Vertex of the parabola through grid points k-1, k, k+1 (the grid point at the ends)."""
    if k == 0 or k == x.numel() - 1 or not bool(torch.isfinite(y[k - 1 : k + 2]).all()):
        return float(x[k])
    y0, y1, y2 = (float(v) for v in y[k - 1 : k + 2])
    h = float(x[k + 1] - x[k])
    den = y0 - 2.0 * y1 + y2
    if den <= 0:
        return float(x[k])
    return float(x[k]) + 0.5 * h * (y0 - y2) / den


def _offset_grid(max_offset: float, step: float) -> Tensor:
    """Candidate offsets ``-max_offset ... max_offset`` in ``step``s, 0 in the middle (``ConfigError`` on bad bounds)."""
    if not (max_offset > 0 and step > 0 and step <= max_offset):
        raise ConfigError(f"max_offset, step: expected 0 < step <= max_offset, got {max_offset}, {step}")
    steps = int(round(max_offset / step))
    return torch.arange(-steps, steps + 1, dtype=torch.float64) * step


def _grid_estimate(offsets: Tensor, cost_at: Callable[[Tensor], Tensor], pairs: int) -> TimeOffsetEstimate:
    """The grid's minimum of ``cost_at`` refined by a parabola, with the costs at 0 and there."""
    cost = cost_at(offsets)
    k = int(torch.argmin(cost))
    best = _parabola_min(offsets, cost, k)
    return TimeOffsetEstimate(
        offset=best, offsets=offsets, cost=cost, pairs=pairs, cost_at_zero=float(cost[offsets.numel() // 2]),
        cost_at_offset=float(cost_at(torch.tensor([best], dtype=torch.float64))[0]), at_edge=k in (0, len(offsets) - 1),
    )


def estimate_attitude_time_offset(
    sequence: Sequence,
    stream: AttitudeStream,
    max_offset: float = 0.08,
    step: float = 0.0025,
    frame_gap: int = 3,
    max_pairs: int = 60,
    batch: int = 8,
    dense: DenseConfig | None = None,
    device: str | torch.device = "cpu",
) -> TimeOffsetEstimate:
    """Estimate the offset to add to image stamps before sampling ``stream`` (module docstring).

    Args:
        sequence: the RGB-D sequence (frames are read by index).
        stream: its attitude stream.
        max_offset: candidates span ``[-max_offset, max_offset]``, seconds.
        step: grid step, seconds.
        frame_gap: pairs are ``(i, i + frame_gap)``.
        max_pairs: at most this many pairs, evenly spread over the sequence.
        batch: pairs registered per call.
        dense: registration settings (default: ``DenseConfig(geometric_weight=10)``, depth-led:
            the depth image is what NI-SLAM's geometry is taken from).
        device: where the registration runs.

    Returns:
        TimeOffsetEstimate.

    Raises:
        ConfigError: bad arguments.
        ShapeError: a sequence too short for one pair, or no pair registered.
    """
    offsets = _offset_grid(max_offset, step)
    if frame_gap < 1 or max_pairs < 1 or batch < 1:
        raise ConfigError(f"frame_gap, max_pairs, batch: expected >= 1, got {frame_gap}, {max_pairs}, {batch}")
    n = len(sequence)
    if n <= frame_gap:
        raise ConfigError(f"sequence {sequence.name}: {n} frames, need more than frame_gap = {frame_gap}")
    dense = dense or DenseConfig(geometric_weight=10.0)
    starts = torch.linspace(0, n - 1 - frame_gap, min(max_pairs, n - frame_gap)).round().long().unique().tolist()
    t_i, t_j, R_ij = [], [], []
    for c in range(0, len(starts), batch):
        chunk = starts[c : c + batch]
        fi = [sequence[i] for i in chunk]
        fj = [sequence[i + frame_gap] for i in chunk]

        def stack(frames, attr):
            x = torch.stack([getattr(f, attr).to(torch.float32) for f in frames]).to(device)
            return x if attr == "rgb" else x.reshape(x.shape[0], 1, x.shape[-2], x.shape[-1])

        res = register_dense(stack(fi, "rgb"), stack(fi, "depth"), stack(fj, "rgb"), stack(fj, "depth"), sequence.camera, None, dense)
        for k in range(len(chunk)):
            if bool(res.success[k]):
                t_i.append(fi[k].geometry_time)
                t_j.append(fj[k].geometry_time)
                R_ij.append(res.T_ij[k, :3, :3].cpu())
    if not R_ij:
        raise TorchSlamError(f"sequence {sequence.name}: no frame pair registered; the time offset cannot be estimated")
    ti = torch.tensor(t_i, dtype=torch.float64)
    tj = torch.tensor(t_j, dtype=torch.float64)
    R = torch.stack(R_ij).to(torch.float64)
    return _grid_estimate(offsets, lambda o: rotation_agreement(stream, ti, tj, R, o), len(R_ij))


def _window_starts(n: int, frames: int, windows: int, apart: int = 3) -> list[tuple[int, int]]:
    """``windows`` runs of consecutive frames, ``frames`` in all, spread evenly over ``n`` frames.

    Runs lie at least ``apart`` frames apart, so that a rotation stream made of their chains has
    a gap between them that it does not interpolate across; where that does not fit, the first
    ``frames`` frames are one run.
    """
    length = frames // windows
    if windows == 1 or length * windows + apart * (windows - 1) > n:
        return [(0, min(n, frames))]
    starts = torch.linspace(0, n - length, windows).round().long().tolist()
    return [(a, a + length) for a in starts]


def estimate_depth_time_offset(
    sequence: Sequence,
    frames: int = 180,
    windows: int = 3,
    frame_gap: int = 3,
    width: int = 160,
    max_offset: float = 0.08,
    step: float = 0.0025,
    batch: int = 8,
    device: str | torch.device = "cpu",
) -> TimeOffsetEstimate:
    """Estimate the depth stream's latency against the colour stream from the images (module docstring).

    The result's ``offset`` is the ``depth_time_offset`` to give the sequence: each depth image
    was taken at its stamp plus it. A sequence that does not move (no rotation to compare)
    gives a flat cost; compare ``cost_at_offset`` with ``cost_at_zero``.

    Args:
        sequence: the RGB-D sequence (frames read by index; ``Frame.geometry_time`` is the depth
            instant as the sequence gives it, so a sequence already shifted is measured from
            there).
        frames: frames registered, at most, in ``windows`` runs of consecutive frames spread
            over the sequence.
        windows: how many runs.
        frame_gap: the colour pairs are ``(i, i + frame_gap)`` within a run.
        width: working width of both registrations, pixels (rotations need little resolution).
        max_offset: candidates span ``[-max_offset, max_offset]``, seconds.
        step: grid step, seconds.
        batch: pairs registered per call.
        device: where the registrations run.

    Returns:
        TimeOffsetEstimate (``offset``: the depth latency, seconds).

    Raises:
        ConfigError: bad arguments, or a sequence too short for one colour pair in a run.
        TorchSlamError: no colour pair lies within the registered runs.
    """
    offsets = _offset_grid(max_offset, step)
    if min(frames, windows, frame_gap, width, batch) < 1:
        raise ConfigError(f"frames, windows, frame_gap, width, batch: expected >= 1, got {frames}, {windows}, {frame_gap}, {width}, {batch}")
    runs = _window_starts(len(sequence), frames, windows)
    if all(b - a <= frame_gap for a, b in runs):
        raise ConfigError(f"sequence {sequence.name}: runs of {runs[0][1] - runs[0][0]} frames, need more than frame_gap = {frame_gap}")
    cam = sequence.camera
    size = {"width": width, "height": max(1, round(width * cam.height / cam.width))}
    geometric = DenseConfig(geometric_weight=1000.0, **size)
    photometric = DenseConfig(geometric_weight=0.0, **size)

    def register(frame: list, pairs: list[tuple[int, int]], cfg: DenseConfig) -> tuple[Tensor, Tensor]:
        R, ok = [], []
        for c in range(0, len(pairs), batch):
            i, j = zip(*pairs[c : c + batch])

            def stack(idx, attr):
                return torch.stack([getattr(frame[k], attr).to(device, torch.float32) for k in idx])

            res = register_dense(stack(i, "rgb"), stack(i, "depth"), stack(j, "rgb"), stack(j, "depth"), cam, None, cfg)
            R.append(res.T_ij[:, :3, :3].to("cpu", torch.float64))
            ok.append(res.success.cpu())
        return torch.cat(R), torch.cat(ok)

    # Run by run (only one run's images are held): the depth images' rotations, each frame's to
    # the next chained from the run's first frame (a rotation stream at the depth instants), and
    # the colour rotations of the run's pairs. A failed link breaks the chain: the pairs whose
    # samples could reach across it (within the search range) are left out.
    t_depth, R_stream, t_i, t_j, R_colour = [], [], [], [], []
    for a, b in runs:
        frame = [sequence[k] for k in range(a, b)]
        n = len(frame)
        if n < 2:
            continue
        R_link, ok_link = register(frame, [(k, k + 1) for k in range(n - 1)], geometric)
        R_chain = [torch.eye(3, dtype=torch.float64)]
        for R in R_link:
            R_chain.append(R_chain[-1] @ R)
        times = torch.tensor([f.geometry_time for f in frame], dtype=torch.float64)
        t_depth.append(times)
        R_stream.append(torch.stack(R_chain))
        pairs = [(k, k + frame_gap) for k in range(n - frame_gap)]
        if not pairs:
            continue
        R_pair, ok_pair = register(frame, pairs, photometric)
        dt = float(times.diff().median())
        reach = int(math.ceil(max_offset / max(dt, 1e-9))) + 1
        broken = [k + 1 for k in range(n - 1) if not bool(ok_link[k])]  # link k joins frames k and k + 1
        for (i, j), R, ok in zip(pairs, R_pair, ok_pair):
            if bool(ok) and not any(i - reach < k <= j + reach for k in broken):
                t_i.append(frame[i].timestamp)
                t_j.append(frame[j].timestamp)
                R_colour.append(R)
    if not R_colour:
        raise TorchSlamError(f"sequence {sequence.name}: no colour pair registered within unbroken runs; the depth latency cannot be estimated")
    t_all = torch.cat(t_depth)
    dt = float(t_all.diff().median())
    # (Its source label is not read here.)
    stream = AttitudeStream(t_all, torch.cat(R_stream), AttitudeSource.GROUNDTRUTH.value)
    ti, tj, R_kept = (torch.tensor(t_i, dtype=torch.float64), torch.tensor(t_j, dtype=torch.float64), torch.stack(R_colour))
    # A depth image taken d after its stamp: the stream's sample for colour instant t is at t - d.
    return _grid_estimate(offsets, lambda d: rotation_agreement(stream, ti, tj, R_kept, -d, max_gap=2.5 * dt), len(R_colour))
