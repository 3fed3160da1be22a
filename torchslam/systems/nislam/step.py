"""One frame of NI-SLAM, as phases that many sequences take together.

A frame passes between the scheduler (``track_frames``) and its sequence's ``NISlam`` in three
public phase calls, four when its match is retried; the batched stages in between belong to the
scheduler and serve every sequence of a step:

=====  ===========================================  ======================================================
phase  call                                         what it does
=====  ===========================================  ======================================================
1      ``NISlam.prepare(frame) -> FrameInput``      attitude at the depth and colour instants; images on the device
(b)    ``backproject([FrameInput]) -> [Cloud]``     one ``rgbd_to_points`` (and grey re-sampling) per camera group
2      ``NISlam.start_match(input, cloud)``         too few points, or the first keyframe; else a ``MatchRequest``
(t)    ``match([MatchRequest]) -> [TrackResult]``   one ``track_step`` for every frame still tracking (+ summaries)
3      ``NISlam.apply_match(request, ...)``         the keyframe policy, fusion, keyframes, loop closure, the record;
                                                    a ``MatchRequest`` again when the match is to be retried
(t)    ``match`` of the retried requests
3'     ``NISlam.apply_match(request, ...)``         the retried match concludes (no further retry)
=====  ===========================================  ======================================================

Every state crossing these calls is a frozen dataclass of this module (``FrameInput``, ``Cloud``,
``MatchRequest``); tensors are (1, ...) rows of the sequence.

On an accelerator a step waits for the device at most three times whatever the number of
sequences: (b) reads the valid-point counts (with the colour-warp fallback flags), each (t) reads
its batch's ``TrackSummary`` rows (``kcc.summarize``); phases 1-3 decide on those host numbers
and never read a device tensor (``tests/systems/test_nislam_device.py`` holds them to it with
``diagnostics.device_audit``). Keyframe steps read back more (the keyframe's colour, ORB).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from ...data.frame import Frame
from ...errors import ConfigError, ShapeError
from ...kcc import (
    KCCFilter, KernelCorrelator, KeyframeMap, TrackResult, TrackSummary, rgbd_to_points, sample_grey, sample_grey_warped,
    summarize, track_step,
)
from ..base import StepReport
from ..batching import groups, row, stack_dataclass, stack_rows

__all__ = ["CameraRig", "Cloud", "FrameInput", "MatchRequest", "PhasedSystem", "backproject", "match", "track_frames"]


@dataclass(frozen=True)
class CameraRig:
    """How one sequence's depth pixels become rays (fixed for the sequence).

    Attributes:
        intrinsics: (1, 4) float32 ``(fx, fy, cx, cy)`` of the (strided) images.
        rays: (H, W, 3) undistorted rays of the kept pixels, or None for an ideal pinhole.
        distortion: the lens's distortion coefficients, or None.
        lens_key: equal for sequences that share rays and lens (one back-projection call), None
            without distortion.
    """

    intrinsics: Tensor
    rays: Tensor | None
    distortion: tuple[float, ...] | None
    lens_key: object


@dataclass(frozen=True)
class FrameInput:
    """Phase 1's result: a frame with its attitude, ready for back-projection.

    Attributes:
        frame: the frame.
        times: (2,) float64 depth and colour instants, seconds.
        R_att: (2, 3, 3) float64 attitude stream (uncorrected) at those instants.
        rgb: (1, 3, H, W) colour on the device (strided view where ``pixel_stride`` > 1).
        depth: (1, 1, H, W) depth, metres.
        camera: the sequence's camera rig.
        resample_grey: sample the grey values where the points appear at the colour instant.
        cloud: the frame's back-projection where it was computed ahead (``NISlam.prepare_ahead``,
            the same ``backproject`` alone), else None: the step back-projects it.
    """

    frame: Frame
    times: Tensor
    R_att: Tensor
    rgb: Tensor
    depth: Tensor
    camera: CameraRig
    resample_grey: bool
    cloud: "Cloud | None" = None

    @property
    def batch_key(self) -> tuple:
        """Inputs with equal keys are back-projected in one call (same rays, lens and image size)."""
        return (self.camera.lens_key, tuple(self.rgb.shape[1:]), tuple(self.depth.shape[1:]), self.rgb.device)


@dataclass(frozen=True)
class Cloud:
    """A frame's point cloud (rows of the batched back-projection).

    Attributes:
        points: (1, N, 3) camera-frame points, metres.
        grey: (1, N) grey values in [0, 1].
        valid: (1, N) bool.
        n_valid: number of valid points.
    """

    points: Tensor
    grey: Tensor
    valid: Tensor
    n_valid: int


@dataclass(frozen=True)
class MatchRequest:
    """Phase 2's (or a retry's) result: a frame to match against its sequence's current keyframe.

    Attributes:
        input: the frame (phase 1).
        cloud: its cloud.
        R_wi: (3, 3) float64 corrected attitude at the depth instant.
        p_pred: (3,) float64 constant-velocity prediction of the position, or None.
        R_kf_frame: (1, 3, 3) rotation from the frame's camera into the keyframe attitude.
        kf_map: the keyframe's fused map (B = 1).
        kf_filter: the keyframe's correlator filter (B = 1).
        resolution: (1,) the keyframe's resolution, metres per pixel.
        correlator: the sequence's kernel correlator.
        retried: the request is the retry of a lost match (its result is final).
        center: (1, 2) content translation the frame's orthographic image is centred on
            (``track_step``'s ``center``: the prediction in the keyframe's attitude frame), or
            None: its own optical axis.
        check_jump: the keyframe policy may test the match against ``p_pred`` for an
            implausible jump; False where the prediction rests on a frame placed on the motion
            prior (a velocity taken from predictions is no evidence against a measurement).
    """

    input: FrameInput
    cloud: Cloud
    R_wi: Tensor
    p_pred: Tensor | None
    R_kf_frame: Tensor
    kf_map: KeyframeMap
    kf_filter: KCCFilter
    resolution: Tensor
    correlator: KernelCorrelator
    retried: bool = False
    center: Tensor | None = None
    check_jump: bool = True

    @property
    def batch_key(self) -> tuple:
        """Requests with equal keys share one ``track_step`` (same settings, cloud size and device)."""
        points = self.cloud.points
        return (self.correlator.cfg, tuple(points.shape[1:]), points.device)


class PhasedSystem(Protocol):
    """What ``track_frames`` needs of a system: its three phases and its stage timings (``NISlam``)."""

    stage_ms: dict[str, float]

    def prepare(self, frame: Frame) -> FrameInput | None: ...

    def start_match(self, input: FrameInput, cloud: Cloud) -> MatchRequest | None: ...

    def apply_match(
        self, request: MatchRequest, res: TrackResult, kf_filter: KCCFilter, summary: TrackSummary
    ) -> MatchRequest | None: ...


def backproject(inputs: list[FrameInput]) -> list[Cloud]:
    """Back-project frames of one camera group (equal ``batch_key``) in one call.

    Grey values are taken at the colour instant where an input asks for it: a rotation-only warp
    per image (``sample_grey_warped``; a per-point projection, ``sample_grey``, only for an item
    whose rotation turns part of the image behind the camera). The valid-point counts and those
    items are read back from the device together, in one transfer.

    Returns:
        One ``Cloud`` per input, rows of the batch.
    """
    cam = inputs[0].camera
    rgb = stack_rows([w.rgb for w in inputs])
    depth = stack_rows([w.depth for w in inputs])
    intrinsics = stack_rows([w.camera.intrinsics for w in inputs])
    points, grey0, valid0 = rgbd_to_points(rgb, depth, intrinsics, rays=cam.rays)
    grey, valid = grey0, valid0
    need = [k for k, w in enumerate(inputs) if w.resample_grey]
    behind = None
    if need:
        # depth camera -> colour camera, from the attitude stream (host) at the two instants
        R_cd = torch.stack([inputs[k].R_att[1].T @ inputs[k].R_att[0] for k in need]).to(points.device, points.dtype)
        every = len(need) == len(inputs)
        idx = None if every else torch.tensor(need, device=points.device)

        def rows(x: Tensor) -> Tensor:
            return x if idx is None else x[idx]

        g, v, b = sample_grey_warped(
            rows(rgb), rows(valid0), R_cd, rows(intrinsics), rays=cam.rays, grey_image=rows(grey0), distortion=cam.distortion
        )
        if idx is None:
            grey, valid, behind = g, v, b
        else:
            grey, valid = grey.index_copy(0, idx, g), valid.index_copy(0, idx, v)
            behind = torch.zeros(len(inputs), dtype=torch.bool, device=points.device).index_copy(0, idx, b)
    counts = valid.sum(dim=1)
    if behind is None:
        host = counts.tolist()
    else:
        host = torch.cat([counts, behind.to(counts.dtype)]).tolist()  # one transfer for both
        flags, host = host[len(inputs):], host[: len(inputs)]
        back = [k for k, f in enumerate(flags) if f]
        if back:  # rare: those items are sampled per point, and their counts read again
            idx = torch.tensor(back, device=points.device)
            R_back = torch.stack([inputs[k].R_att[1].T @ inputs[k].R_att[0] for k in back]).to(points.device, points.dtype)
            g, v = sample_grey(rgb[idx], points[idx], valid0[idx], R_back, intrinsics[idx], grey0[idx], cam.distortion)
            grey, valid = grey.index_copy(0, idx, g.to(grey.dtype)), valid.index_copy(0, idx, v)
            for k, n in zip(back, v.sum(dim=1).tolist()):
                host[k] = n
    return [Cloud(points[k : k + 1], grey[k : k + 1], valid[k : k + 1], int(host[k])) for k in range(len(inputs))]


def match(requests: list[MatchRequest]) -> tuple[list[TrackResult], list[KCCFilter], list[TrackSummary]]:
    """One ``track_step`` for requests of one group (equal ``batch_key``), each against its own keyframe.

    Returns:
        Per request its ``TrackResult``, its filter as a row of the stacked batch (kept as the
        keyframe's filter, the next step stacks it without a copy; the maps are not kept: most
        frames fuse into theirs, which replaces it anyway) and its host-side numbers, read back
        for the whole group in one transfer (``summarize``).
    """
    kf_filter = stack_dataclass([r.kf_filter for r in requests])
    center = None
    if any(r.center is not None for r in requests):
        center = torch.cat([r.center if r.center is not None else r.cloud.points.new_zeros(1, 2) for r in requests])
    res = track_step(
        stack_rows([r.cloud.points for r in requests]),
        stack_rows([r.cloud.grey for r in requests]),
        stack_rows([r.cloud.valid for r in requests]),
        torch.cat([r.R_kf_frame for r in requests]),
        stack_dataclass([r.kf_map for r in requests]),
        kf_filter,
        torch.cat([r.resolution for r in requests]),
        requests[0].correlator,
        center,
    )
    summaries = summarize(res)
    if len(requests) == 1:
        return [res], [kf_filter], summaries
    return [row(res, k) for k in range(len(requests))], [row(kf_filter, k) for k in range(len(requests))], summaries


def track_frames(systems: list[PhasedSystem], frames: list[Frame], max_batch: int | None = None) -> StepReport:
    """Advance NI-SLAM systems (one per sequence, each started) by one frame each, batching the heavy stages.

    Every system keeps its own keyframes, attitude stream, loop closure and pose graph; only the
    per-frame tensor work (back-projection, tracking step) is shared, in the phases of the module
    docstring. Fusion, keyframes and loop closure run per system. The result of each system
    equals what ``NISlam.track`` alone gives, to floating-point round-off of the batched kernels
    (``NISlam.track`` is this function with one system).

    Args:
        systems: started ``NISlam`` instances.
        frames: the next frame of each system's sequence.
        max_batch: the most systems in one batched call; systems are split in consecutive
            groups of this size (None: all together).

    Returns:
        StepReport. A phase that raises marks only its own system; a batched call that raises is
        repeated one system at a time so the failure lands on the system that caused it.

    Raises:
        ShapeError: ``frames`` does not hold one frame per system.
        ConfigError: ``max_batch`` is not a positive integer.
    """
    if len(frames) != len(systems):
        raise ShapeError(f"frames: expected one frame per system ({len(systems)}), got {len(frames)}")
    if max_batch is not None and not (isinstance(max_batch, int) and max_batch >= 1):
        raise ConfigError(f"max_batch: expected a positive integer or None, got {max_batch!r}")
    n = len(systems)
    step = _Step(systems)
    size = max_batch or max(n, 1)
    for lo in range(0, n, size):
        step.advance(list(range(lo, min(lo + size, n))), frames)
    return StepReport(errors=step.errors, compute_s=step.seconds)


class _Step:
    """Bookkeeping of one ``track_frames`` call: per-system errors and seconds."""

    def __init__(self, systems: list[PhasedSystem]) -> None:
        self.systems = systems
        self.errors: list[Exception | None] = [None] * len(systems)
        self.seconds = [0.0] * len(systems)

    def own(self, i: int, stage: str | None, fn: Callable, *args):
        """Run one system's phase: timed, charged to it, and its failure caught. None after a failure."""
        t0 = time.perf_counter()
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001 - one failing sequence must not stop the others
            self.errors[i] = exc
            return None
        finally:
            self._charge(i, stage, time.perf_counter() - t0)

    def _charge(self, i: int, stage: str | None, dt: float) -> None:
        self.seconds[i] += dt
        if stage is not None:
            ms = self.systems[i].stage_ms
            ms[stage] = ms.get(stage, 0.0) + 1000.0 * dt

    def batched(self, items: list[int], stage: str, fn: Callable[[list[int]], list], out: dict[int, object]) -> None:
        """``out[i]`` for ``i`` in ``items`` from one ``fn(items)``, its time split evenly among them.

        If it raises for several items, it runs once per item so the failure is attributed.
        """
        if not items:
            return
        t0 = time.perf_counter()
        try:
            values = fn(items)
        except Exception as exc:  # noqa: BLE001 - see ``own``
            values = exc
        share = (time.perf_counter() - t0) / len(items)
        for i in items:
            self._charge(i, stage, share)
        if not isinstance(values, Exception):
            out.update(zip(items, values))
        elif len(items) == 1:
            self.errors[items[0]] = values
        else:
            for i in items:
                self.batched([i], stage, fn, out)

    def advance(self, chunk: list[int], frames: list[Frame]) -> None:
        """Take the systems ``chunk`` (indices) through every phase of one frame (see the module docstring)."""
        systems = self.systems
        inputs = {}
        for i in chunk:
            inputs[i] = self.own(i, "backproject", systems[i].prepare, frames[i])
        live = [i for i in chunk if inputs[i] is not None]
        clouds: dict[int, Cloud] = {i: inputs[i].cloud for i in live if inputs[i].cloud is not None}
        for group in groups([i for i in live if i not in clouds], lambda i: inputs[i].batch_key):
            self.batched(group, "backproject", lambda items: backproject([inputs[i] for i in items]), clouds)
        requests = {}
        for i in chunk:
            if i in clouds:
                requests[i] = self.own(i, None, systems[i].start_match, inputs[i], clouds[i])
        for _ in range(2):  # the match, then the retried matches
            pending = [i for i in chunk if requests.get(i) is not None]
            retries = {}
            for group in groups(pending, lambda i: requests[i].batch_key):
                results: dict[int, tuple[TrackResult, KCCFilter, TrackSummary]] = {}
                self.batched(group, "kcc", lambda items: list(zip(*match([requests[i] for i in items]))), results)
                for i in group:
                    if i in results:
                        retries[i] = self.own(i, None, systems[i].apply_match, requests[i], *results[i])
            requests = retries
