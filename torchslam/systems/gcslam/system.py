"""GC-SLAM: frame-to-keyframe registration, MILD loop detection and FastGO (paper §IV).

Two threads, as in the paper:

* **tracking** (the caller's thread): every frame is registered to the latest keyframe, by ORB
  features (``frontend: sparse``, :mod:`torchslam.registration.sparse`) or by dense
  photometric + geometric alignment (``frontend: dense``, :mod:`torchslam.registration.dense`).
  A frame whose keyframe's points have moved by more than ``keyframe_displacement * f`` pixels on
  average becomes a new keyframe; the correspondences of its registration become the statistics
  of the pair (previous keyframe, new keyframe). Frames keep their pose relative to their
  keyframe and are re-posed from the optimised keyframes at the end.
* **optimisation** (a background thread, or inline with ``threaded: false``): for each new
  keyframe in insertion order, MILD (multi-index hashing of ORB descriptors, no trained
  vocabulary) proposes the ``top_k`` most similar earlier keyframes; they are registered to the
  new keyframe with sparse registration all at once; FastGO runs ``fastgo_iterations`` Gauss-
  Newton iterations over all keyframes; candidate loops are kept only if the registration
  error of the earlier pairs does not rise by more than ``loop_threshold`` (5 %) after
  re-optimisation (§IV-C), otherwise poses and pairs are rolled back.

The optimisation thread owns the keyframe poses and computes each new keyframe's initial pose
from its own (optimised) estimate of the reference keyframe, so the threaded and the
synchronous modes give the same result; only the wall time differs.

When a frame cannot be registered (too few inliers or correspondences), the tracker tries to
relocalise it against the last ``relocalize_keyframes`` keyframes with sparse registration; a
success makes the frame a keyframe linked to the one it matched. Otherwise the frame keeps the
pose of the last tracked frame and is counted as lost; after ``max_lost`` lost frames in a row,
the next frame with enough depth starts a new keyframe with no link, which FastGO gauges on its
own until a loop closure reconnects it.

Convention:
    The world is the first keyframe's camera frame (FastGO holds keyframe 0 fixed at the
    identity); trajectory, keyframes and ``map.ply`` (the keyframes' coloured depth points in
    their optimised poses) are all in it.
"""

from __future__ import annotations

import bisect
import functools
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from ...data.frame import Frame, Sequence
from ...data.trajectory import Trajectory
from ...errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, ShapeError, TorchSlamError, check_limits
from ...fastgo import (
    FastGOConfig,
    FastGOProblem,
    PairStats,
    accept_loop_closures,
    optimize,
    optimize_batch,
)
from ...features import ORBConfig
from ...geometry import (
    PinholeCamera,
    backproject_depth,
    project_points,
    se3_inverse,
    undistorted_rays,
)
from ...loop import MILDConfig, MILDDatabase
from ...registration.dense import DenseConfig, prepare_dense_frame, register_dense_frames
from ...registration.sparse import (
    FrameFeatures,
    SparseConfig,
    frame_features,
    register_sparse,
    register_sparse_batch,
)
from ..base import StepReport, SystemOutput, add_stage_ms, empty_output, frame_poses, resample_poses
from ..monitor import Monitor
from ..framelog import voxel_downsample
from ..memory import DENSE_BYTES_PER_WORKING_PIXEL
from ..registry import LockstepSpec, SystemSpec

__all__ = ["SPEC", "GCSlam", "GCSlamConfig", "insert_keyframes", "track_frames"]

logger = logging.getLogger(__name__)

FRONTENDS = ("sparse", "dense")


@dataclass(frozen=True)
class GCSlamConfig:
    """Settings of GC-SLAM. Defaults follow the authors' released code where the paper is silent.

    Attributes:
        frontend: ``sparse`` (ORB registration) or ``dense`` (photometric + geometric).
        orb_features: ORB features per frame (released code: 2000).
        orb_scale: ORB pyramid scale factor (1.2).
        orb_levels: ORB pyramid levels (8).
        sparse: sparse registration settings (isometry filter, RANSAC, refinement).
        dense: dense registration settings (320x240 pyramid).
        keyframe_displacement: a frame becomes a keyframe when the keyframe's points move by
            more than this fraction of the focal length on average (released code: 0.1).
        keyframe_sample_stride: pixel stride of the keyframe points used for that test.
        mild: loop detector settings (16 tables of 16-bit substrings, top 5 candidates).
        loops: look for loop closures at every new keyframe.
        fastgo_iterations: FastGO Gauss-Newton iterations per keyframe (released code: 3).
        loop_iterations: iterations of the trial optimisation that tests loop candidates.
        loop_threshold: reject loops that raise the RMS registration error of the earlier pairs
            by more than this fraction (released code: 5 %) plus ``loop_slack_m``.
        loop_slack_m: absolute slack of that test, metres. Real registrations are biased by
            millimetres (colour/depth timing, rolling shutter), so a true loop over a chain of
            such pairs raises their RMS error by 1-2 mm: on TUM fr1/xyz the 5 % rule alone
            rejected 34 of 59 true loops (ATE 5.5 cm instead of 2.3 cm). A false loop moves the
            error by centimetres.
        final_iterations: iterations of one last FastGO run over all keyframes at the end of
            the sequence (0: keep the per-keyframe result).
        threaded: run optimisation in a background thread (False: inline, for tests).
        relocalize_keyframes: recent keyframes tried when a frame cannot be registered.
        max_lost: lost frames in a row before a new, unlinked keyframe is started.
        min_valid_depth: frames with fewer valid depth pixels are not tracked.
        interpolation_max_gap: largest gap between depth instants across which the trajectory is
            interpolated to the colour timestamps, seconds.
        map_stride: pixel stride of the keyframe clouds in ``map.ply``.
        map_voxel: voxel size of ``map.ply``, metres.
        max_depth: depth beyond this is ignored for the map, metres.
    """

    frontend: str = "sparse"
    orb_features: int = 2000
    orb_scale: float = 1.2
    orb_levels: int = 8
    sparse: SparseConfig = field(default_factory=SparseConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    keyframe_displacement: float = 0.1
    keyframe_sample_stride: int = 16
    mild: MILDConfig = field(default_factory=MILDConfig)
    loops: bool = True
    fastgo_iterations: int = 3
    loop_iterations: int = 10
    loop_threshold: float = 0.05
    loop_slack_m: float = 0.003
    final_iterations: int = 10
    threaded: bool = True
    relocalize_keyframes: int = 5
    max_lost: int = 10
    min_valid_depth: int = 1000
    interpolation_max_gap: float = 0.1
    map_stride: int = 4
    map_voxel: float = 0.01
    max_depth: float = 5.0

    LIMITS: ClassVar[dict[str, Limit]] = {
        "orb_features": AT_LEAST_1, "orb_scale": Limit(gt=1), "orb_levels": AT_LEAST_1, "keyframe_displacement": POSITIVE,
        "keyframe_sample_stride": AT_LEAST_1, "fastgo_iterations": AT_LEAST_1, "loop_iterations": AT_LEAST_1,
        "loop_threshold": NON_NEGATIVE, "loop_slack_m": NON_NEGATIVE, "final_iterations": NON_NEGATIVE,
        "relocalize_keyframes": NON_NEGATIVE, "max_lost": NON_NEGATIVE, "min_valid_depth": AT_LEAST_1,
        "interpolation_max_gap": POSITIVE, "map_stride": AT_LEAST_1, "map_voxel": POSITIVE, "max_depth": POSITIVE,
    }

    def __post_init__(self) -> None:
        if self.frontend not in FRONTENDS:
            raise ConfigError(f"frontend: {self.frontend!r} is not one of {list(FRONTENDS)}")
        check_limits(self)

    def orb(self) -> ORBConfig:
        return ORBConfig(n_features=self.orb_features, scale_factor=self.orb_scale, n_levels=self.orb_levels)


@dataclass
class _KeyframeEvent:
    """What the tracker hands the optimiser for one new keyframe."""

    kf: int  # keyframe id (0, 1, ...)
    reference: int | None  # keyframe it was registered to, None for an unlinked keyframe
    T_ref_kf: Tensor | None  # (4, 4) float64 relative pose, p_ref = T p_kf
    stats: PairStats | None  # statistics of that registration's correspondences
    features: FrameFeatures  # ORB features of the keyframe (for MILD and loop registration)
    anchor: tuple[int, Tensor] | None = None  # unlinked keyframe: (keyframe, pose relative to it) of the last tracked frame
    frame_index: int = 0  # the keyframe's sequence frame index (the TensorBoard step)


class _Optimizer:
    """Keyframe poses, pairs, the MILD database and FastGO: the optimisation thread's state.

    Poses and pair statistics live on the CPU in float64 whatever device the front-end uses
    (FastGO's cost does not grow with images, and float64 is the back-end's precision).
    """

    def __init__(self, cfg: GCSlamConfig, monitor: Monitor) -> None:
        self.cfg = cfg
        self.monitor = monitor
        self.T_wk: list[Tensor] = []
        self.pairs: list[tuple[int, int]] = []
        self.stats: list[PairStats] = []
        self.pair_kind: list[str] = []  # "odometry", "relocalization" or "loop"
        self.features: list[FrameFeatures] = []
        self.mild = MILDDatabase(cfg.mild)
        self.loops = {"candidates": 0, "registered": 0, "accepted": 0, "rejected": 0}
        self.stage_ms: dict[str, float] = {}
        self.fastgo_ms: list[float] = []
        self.generator = torch.Generator().manual_seed(cfg.sparse.seed + 1)

    def _add_ms(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    def _fastgo_config(self, iterations: int) -> FastGOConfig:
        return FastGOConfig(iterations=iterations)

    def _problem(self) -> tuple[Tensor, Tensor, PairStats]:
        T = torch.stack(self.T_wk)
        if not self.pairs:
            return T, torch.zeros(0, 2, dtype=torch.int64), PairStats.empty(0)
        return T, torch.tensor(self.pairs, dtype=torch.int64), PairStats.cat(self.stats)

    def insert(self, ev: _KeyframeEvent) -> None:
        """Take one new keyframe: pose, odometry pair, MILD, FastGO, loop closures."""
        (error,) = insert_keyframes([self], [ev])
        if error is not None:
            raise error

    def _begin(self, ev: _KeyframeEvent) -> list[int]:
        """Add the keyframe and its odometry pair; query and update MILD; return loop candidates."""
        cfg = self.cfg
        if ev.kf != len(self.T_wk):
            raise TorchSlamError(f"keyframe {ev.kf} inserted out of order (expected {len(self.T_wk)})")
        if ev.reference is None:
            # An unlinked keyframe starts where the last tracked frame was; that guess only
            # matters until a loop closure links it to the rest.
            T0 = torch.eye(4, dtype=torch.float64)
            if ev.anchor is not None:
                T0 = self.T_wk[ev.anchor[0]] @ ev.anchor[1].to(torch.float64)
            self.T_wk.append(T0)
        else:
            self.T_wk.append(self.T_wk[ev.reference] @ ev.T_ref_kf.to(torch.float64))
            self.pairs.append((ev.reference, ev.kf))
            self.stats.append(ev.stats.to("cpu", torch.float64))
            self.pair_kind.append("odometry")
        self.features.append(ev.features)
        t0 = time.perf_counter()
        candidates: list[int] = []
        if cfg.loops and len(self.mild):
            ids, _ = self.mild.query(ev.features.descriptors)
            candidates = [int(c) for c in ids if int(c) != ev.reference]
        self.mild.add(ev.kf, ev.features.descriptors)
        self._add_ms("loop_detection", t0)
        return candidates

    def _optimized(self, res, frame_index: int, ms: float) -> None:
        """Take the result of the per-keyframe FastGO run (``ms``: its share of the time)."""
        self.T_wk = list(res.T_wc.unbind(0))
        self.fastgo_ms.append(ms)
        self.stage_ms["fastgo"] = self.stage_ms.get("fastgo", 0.0) + ms
        self.monitor.scalar("optimization/fastgo_ms", ms, frame_index)

    def _close_loops(self, kf: int, candidates: list[int], frame_index: int = 0) -> None:
        cfg = self.cfg
        t0 = time.perf_counter()
        self.loops["candidates"] += len(candidates)
        res = register_sparse_batch([self.features[c] for c in candidates], [self.features[kf]] * len(candidates), cfg.sparse, self.generator)
        ok = [b for b in range(len(candidates)) if bool(res.success[b])]
        t0 = self._add_ms("loop_registration", t0)
        if not ok:
            return
        self.loops["registered"] += len(ok)
        # All verified candidates are tested together; if that is rejected, each on its own, so
        # one false candidate does not take the true ones down with it.
        trials = [ok] if len(ok) == 1 else [ok] + [[b] for b in ok]
        for k, group in enumerate(trials):
            T, pairs, stats = self._problem()
            loop_pairs = torch.tensor([(candidates[b], kf) for b in group], dtype=torch.int64)
            loop_stats = res.stats[torch.tensor(group, device=res.stats.device)].to("cpu", torch.float64)
            decision = accept_loop_closures(
                T, pairs, stats, loop_pairs, loop_stats, fixed=0, threshold=float("inf"),
                config=self._fastgo_config(cfg.loop_iterations),
            )
            rms_before, rms_after = decision.cost_before**0.5, decision.cost_after**0.5
            accepted = rms_after <= rms_before * (1.0 + cfg.loop_threshold) + cfg.loop_slack_m
            if accepted:
                self.T_wk = list(decision.result.T_wc.unbind(0))
                for b in group:
                    self.pairs.append((candidates[b], kf))
                    self.pair_kind.append("loop")
                self.stats.append(loop_stats)
                self.loops["accepted"] += len(group)
                self.monitor.scalar("progress/loops_accepted", self.loops["accepted"], frame_index)
                logger.debug("keyframe %d: loop(s) to %s accepted (RMS %.4f -> %.4f m)", kf, [candidates[b] for b in group],
                             rms_before, rms_after)
                if k == 0:
                    break
            else:
                if k > 0 or len(group) == 1:
                    self.loops["rejected"] += len(group)
        self._add_ms("loop_acceptance", t0)

    def finish(self) -> None:
        if self.cfg.final_iterations and self.pairs:
            t0 = time.perf_counter()
            T, pairs, stats = self._problem()
            res = optimize(T, pairs, stats, fixed=0, config=self._fastgo_config(self.cfg.final_iterations))
            self.T_wk = list(res.T_wc.unbind(0))
            self._add_ms("fastgo_final", t0)


def insert_keyframes(optimizers: list[_Optimizer], events: list[_KeyframeEvent]) -> list[Exception | None]:
    """Insert one new keyframe into each of several optimisers (one per sequence) at once.

    Each optimiser adds its keyframe and queries MILD; then ONE FastGO call (``optimize_batch``)
    runs ``fastgo_iterations`` over all their pose graphs together (each with its own damping
    and convergence); finally each closes its loops. With one optimiser this is exactly the
    per-keyframe step of a single sequence; with several each gets the result it gets alone,
    since the problems of a batch do not interact.

    Returns:
        Per optimiser the exception that stopped its step (its state is then undefined), or None.
        A joint FastGO call that raises is repeated one problem at a time to place the failure.
    """
    errors: list[Exception | None] = [None] * len(optimizers)
    candidates: list[list[int]] = [[] for _ in optimizers]
    for k, (o, ev) in enumerate(zip(optimizers, events)):
        try:
            candidates[k] = o._begin(ev)
        except Exception as exc:  # noqa: BLE001 - reported in the optimiser's place
            errors[k] = exc
    idx = [k for k, o in enumerate(optimizers) if errors[k] is None and o.pairs]
    groups = [idx] if idx else []
    while groups:
        group = groups.pop(0)
        t0 = time.perf_counter()
        try:
            problems = [FastGOProblem(*optimizers[k]._problem(), 0) for k in group]
            o0 = optimizers[group[0]]
            res = optimize_batch(problems, o0._fastgo_config(o0.cfg.fastgo_iterations))
        except Exception as exc:  # noqa: BLE001
            if len(group) == 1:
                errors[group[0]] = exc
            else:
                groups.extend([k] for k in group)
            continue
        share = 1000.0 * (time.perf_counter() - t0) / len(group)
        for j, k in enumerate(group):
            optimizers[k]._optimized(res.problem(j), events[k].frame_index, share)
    for k, (o, ev) in enumerate(zip(optimizers, events)):
        if errors[k] is None and candidates[k]:
            try:
                o._close_loops(ev.kf, candidates[k], ev.frame_index)
            except Exception as exc:  # noqa: BLE001
                errors[k] = exc
    return errors


class _Worker:
    """Runs an :class:`_Optimizer` in a background thread, inline, or deferred.

    Deferred (lockstep runs of several sequences): new keyframes wait in ``pending`` until the
    driver inserts those of all sequences together (:func:`track_frames`).
    """

    def __init__(self, optimizer: _Optimizer, threaded: bool, deferred: bool = False) -> None:
        self.optimizer = optimizer
        self.threaded = threaded and not deferred
        self.deferred = deferred
        self.pending: list[_KeyframeEvent] = []
        self.error: BaseException | None = None
        if self.threaded:
            self.queue: queue.Queue = queue.Queue()
            self.thread = threading.Thread(target=self._loop, name="torchslam-gcslam-optimizer", daemon=True)
            self.thread.start()

    def _loop(self) -> None:
        while True:
            ev = self.queue.get()
            if ev is None:
                return
            if self.error is not None:
                continue
            try:
                self.optimizer.insert(ev)
            except BaseException as exc:  # noqa: BLE001 - reported to the tracking thread at the next call
                self.error = exc

    def submit(self, ev: _KeyframeEvent) -> None:
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error
        if self.threaded:
            self.queue.put(ev)
        elif self.deferred:
            self.pending.append(ev)
        else:
            self.optimizer.insert(ev)

    def join(self) -> None:
        while self.pending:
            self.optimizer.insert(self.pending.pop(0))
        if self.threaded:
            self.queue.put(None)
            self.thread.join()
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error


@dataclass
class _TrackKeyframe:
    """What the tracker keeps of a keyframe."""

    kf: int
    frame_index: int
    features: FrameFeatures
    sample_points: Tensor  # (S, 3) float64 keyframe-frame points for the displacement test
    sample_pixels: Tensor  # (S, 2) float64 their pixels in the keyframe
    dense: Any | None  # the dense pyramid of the current keyframe only (dense front-end); None for older ones
    map_points: Tensor  # (P, 3) float32 keyframe-frame points of map.ply
    map_colors: Tensor  # (P, 3) float32


class GCSlam:
    """GC-SLAM on one sequence; see the module docstring."""

    name = "gcslam"

    def __init__(
        self, cfg: GCSlamConfig | None = None, device: str | torch.device = "cpu", monitor: Monitor | None = None,
        deferred: bool = False,
    ):
        """
        Args:
            cfg: settings.
            device: where the front-end's tensors live.
            monitor: TensorBoard (or no-op) monitor.
            deferred: leave new keyframes for :func:`track_frames` to optimise together with
                those of other sequences (lockstep runs); overrides ``cfg.threaded``.
        """
        self.cfg = cfg or GCSlamConfig()
        self.device = torch.device(device)
        self.monitor = monitor or Monitor()
        self.deferred = deferred
        self._worker: _Worker | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, sequence: Sequence) -> None:
        cfg = self.cfg
        self.sequence_name = sequence.name
        self.camera: PinholeCamera = sequence.camera
        self.intrinsics = self.camera.as_tensor(torch.float64, self.device)[None]
        self.rays = undistorted_rays(self.camera, torch.float64, self.device) if self.camera.has_distortion else None
        self.orb_cfg = cfg.orb()
        self.optimizer = _Optimizer(cfg, self.monitor)
        self._worker = _Worker(self.optimizer, cfg.threaded, deferred=self.deferred)
        self.keyframes: list[_TrackKeyframe] = []
        self.frame_index: list[int] = []
        self.frame_time: list[float] = []
        self.frame_geom_time: list[float] = []
        self.frame_kf: list[int] = []
        self.frame_T_kf: list[Tensor] = []
        # Per recorded frame: "lost" (holds the last pose), "unlinked" (an unlinked keyframe
        # started at the last pose: a motion prior until a loop closure links it) or None.
        self.frame_prior: list[str | None] = []
        self.lost_in_row = 0
        self.counts = {"lost_frames": 0, "relocalized": 0, "unlinked_keyframes": 0, "no_depth": 0, "tracking_failures": 0}
        self.inliers: list[int] = []
        self.stage_ms: dict[str, float] = {}
        self.generator = torch.Generator().manual_seed(cfg.sparse.seed)
        self._last_T_kf = torch.eye(4, dtype=torch.float64, device=self.device)
        self._need_unlinked = False
        self._inline_s = 0.0
        self.last_frame_index: int | None = None  # the frame last given to ``track`` (TensorBoard step)

    def _toc(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    # ------------------------------------------------------------------ tracking
    def track(self, frame: Frame) -> None:
        cfg = self.cfg
        t0 = time.perf_counter()
        self.last_frame_index = frame.index
        rgb = frame.rgb.to(self.device)
        depth = frame.depth.to(self.device)
        if int((depth > 0).sum()) < cfg.min_valid_depth:
            self.counts["no_depth"] += 1
            self._record_lost(frame)
            return
        need_orb = cfg.frontend == "sparse" or not self.keyframes or self._need_unlinked
        feats = self._features(rgb, depth) if need_orb else None
        t0 = self._toc("orb_extraction", t0) if need_orb else t0
        dense_frame = prepare_dense_frame(rgb[None], depth[None], self.camera, cfg.dense) if cfg.frontend == "dense" else None
        if cfg.frontend == "dense":
            t0 = self._toc("dense_preparation", t0)
        if not self.keyframes or self._need_unlinked:
            self._new_keyframe(frame, rgb, depth, feats, dense_frame, reference=None, T_ref=None, stats=None)
            self._need_unlinked = False
            self._toc("keyframe_insertion", t0 + self._take_inline())
            return
        kf = self.keyframes[-1]
        if cfg.frontend == "sparse":
            res = register_sparse(kf.features, feats, cfg.sparse, self.generator)
            ok, T_kf, stats, n = bool(res.success[0]), res.T_ij[0], res.stats, int(res.num_inliers[0])
        else:
            res = register_dense_frames(kf.dense, dense_frame, self._last_T_kf[None], cfg.dense)
            ok, T_kf, stats, n = bool(res.success[0]), res.T_ij[0], res.stats, int(res.num_correspondences[0])
        t0 = self._toc("registration", t0)
        if not ok:
            self.counts["tracking_failures"] += 1
            self._relocalize(frame, rgb, depth, feats, dense_frame)
            self._toc("relocalization", t0 + self._take_inline())
            return
        self.lost_in_row = 0
        self.inliers.append(n)
        self.monitor.scalar("tracking/correspondences", n, frame.index)
        moved = self._displacement(kf, T_kf)
        t0 = self._toc("keyframe_decision", t0)
        if moved > cfg.keyframe_displacement * self.camera.fx:
            if feats is None:
                feats = self._features(rgb, depth)
                t0 = self._toc("orb_extraction", t0)
            self._new_keyframe(frame, rgb, depth, feats, dense_frame, reference=kf.kf, T_ref=T_kf, stats=stats)
            self._toc("keyframe_insertion", t0 + self._take_inline())
            return
        self._record(frame, kf.kf, T_kf)

    def _take_inline(self) -> float:
        s, self._inline_s = self._inline_s, 0.0
        return s

    def _features(self, rgb: Tensor, depth: Tensor) -> FrameFeatures:
        return frame_features(rgb, depth, self.camera, self.orb_cfg, self.cfg.sparse, rays=self.rays)

    def _displacement(self, kf: _TrackKeyframe, T_kf_frame: Tensor) -> float:
        """Mean pixel displacement of the keyframe's sample points seen from the frame."""
        if not len(kf.sample_points):
            return float("inf")
        T = se3_inverse(T_kf_frame.to(torch.float64))
        p = kf.sample_points @ T[:3, :3].T + T[:3, 3]
        uv, ok = project_points(p[None], self.intrinsics)
        ok = ok[0]
        if not bool(ok.any()):
            return float("inf")
        return float((uv[0][ok] - kf.sample_pixels[ok]).norm(dim=-1).mean())

    def _relocalize(self, frame: Frame, rgb: Tensor, depth: Tensor, feats: FrameFeatures | None, dense_frame) -> None:
        cfg = self.cfg
        recent = self.keyframes[-cfg.relocalize_keyframes:] if cfg.relocalize_keyframes else []
        if recent:
            if feats is None:
                feats = self._features(rgb, depth)
            res = register_sparse_batch([k.features for k in recent], [feats] * len(recent), cfg.sparse, self.generator)
            good = res.success.nonzero().flatten()
            if len(good):
                b = int(good[torch.argmax(res.num_inliers[good])])
                self.counts["relocalized"] += 1
                self.lost_in_row = 0
                self._new_keyframe(frame, rgb, depth, feats, dense_frame, reference=recent[b].kf, T_ref=res.T_ij[b],
                                   stats=res.stats[torch.tensor([b], device=res.stats.device)], relocalized=True)
                return
        self._record_lost(frame)
        if self.lost_in_row > cfg.max_lost:
            self._need_unlinked = True

    def _record_lost(self, frame: Frame) -> None:
        self.counts["lost_frames"] += 1
        self.lost_in_row += 1
        if not self.frame_index:
            return  # nothing to hold yet: the frame has no pose
        self.frame_prior.append("lost")
        self.frame_index.append(frame.index)
        self.frame_time.append(frame.timestamp)
        self.frame_geom_time.append(frame.geometry_time)
        self.frame_kf.append(self.frame_kf[-1])
        self.frame_T_kf.append(self.frame_T_kf[-1])

    def _record(self, frame: Frame, kf: int, T_kf: Tensor, prior: str | None = None) -> None:
        self.frame_prior.append(prior)
        self.frame_index.append(frame.index)
        self.frame_time.append(frame.timestamp)
        self.frame_geom_time.append(frame.geometry_time)
        self.frame_kf.append(kf)
        T = T_kf.to(torch.float64)
        self.frame_T_kf.append(T)
        self._last_T_kf = T

    def _new_keyframe(self, frame, rgb, depth, feats, dense_frame, reference, T_ref, stats, relocalized: bool = False) -> None:
        cfg = self.cfg
        if feats is None:
            feats = self._features(rgb, depth)
        kid = len(self.keyframes)
        points, valid = backproject_depth(depth[None].to(torch.float64), self.intrinsics, rays=self.rays)
        points, valid = points[0], valid[0] & (points[0, :, 2] <= cfg.max_depth)
        H, W = depth.shape[-2:]
        idx = torch.arange(H * W, device=self.device).view(H, W)
        s = cfg.keyframe_sample_stride
        sample = idx[s // 2 :: s, s // 2 :: s].reshape(-1)
        sample = sample[valid[sample]]
        # Their pixels as ``_displacement`` projects them (pinhole, along the undistorted rays),
        # so the displacement is exactly 0 at the keyframe's own pose even with lens distortion
        # (the raw pixel grid differs from that by ~5 px on average on TUM fr1).
        pix = project_points(points[sample][None], self.intrinsics)[0][0]
        m = idx[:: cfg.map_stride, :: cfg.map_stride].reshape(-1)
        m = m[valid[m]]
        colors = rgb.reshape(3, -1)[:, m].T.float()
        anchor = None
        if reference is None and self.frame_index:
            anchor = (self.frame_kf[-1], self.frame_T_kf[-1].cpu())
            self.counts["unlinked_keyframes"] += 1
        if self.keyframes:
            self.keyframes[-1].dense = None  # only the current keyframe is registered against densely
        self.keyframes.append(
            _TrackKeyframe(kid, frame.index, feats, points[sample], pix, dense_frame, points[m].float(), colors)
        )
        ev = _KeyframeEvent(kid, reference, None if T_ref is None else T_ref.to(torch.float64).cpu(),
                            None if stats is None else stats.to("cpu", torch.float64), feats, anchor, frame.index)
        t_submit = time.perf_counter()
        self._worker.submit(ev)
        if not self._worker.threaded:
            # Inline optimisation is reported under the optimiser's own stages, not the tracker's.
            self._inline_s += time.perf_counter() - t_submit
        self._record(frame, kid, torch.eye(4, dtype=torch.float64, device=self.device), prior="unlinked" if anchor is not None else None)
        self.monitor.scalar("progress/keyframes", kid + 1, frame.index)

    # ------------------------------------------------------------------ monitoring
    def estimate_so_far(self) -> Trajectory | None:
        """The frames tracked so far, posed from the keyframes the optimiser has processed.

        With the background thread, frames of keyframes still queued are left out. Poses are at
        the depth instants (not re-sampled to colour stamps until ``finish``).
        """
        T_wk = list(self.optimizer.T_wk)  # a snapshot: the thread only appends or replaces the list
        # Keyframe ids never decrease along the frames, so the posed frames are a prefix.
        n = bisect.bisect_left(self.frame_kf, len(T_wk))
        if n == 0:
            return None
        T = frame_poses(torch.stack(T_wk), self.frame_kf[:n], self.frame_T_kf[:n])
        return Trajectory(torch.tensor(self.frame_geom_time[:n], dtype=torch.float64), T)

    def progress_counters(self) -> dict[str, float]:
        """Keyframes, loops and lost frames so far, for TensorBoard."""
        loops = dict(self.optimizer.loops)
        return {
            "keyframes": float(len(self.keyframes)),
            "loops_accepted": float(loops["accepted"]),
            "loops_rejected": float(loops["rejected"]),
            "lost_frames": float(self.counts["lost_frames"]),
            "prior_frames": float(sum(p is not None for p in self.frame_prior)),
        }

    # ------------------------------------------------------------------ output
    def finish(self) -> SystemOutput:
        if self._worker is None:
            raise TorchSlamError("GCSlam.finish() called before start()")
        t0 = time.perf_counter()
        self._worker.join()
        opt = self.optimizer
        opt.finish()
        self._toc("wait_optimizer", t0)
        stage_ms = dict(self.stage_ms)
        for k, v in opt.stage_ms.items():
            stage_ms[f"optimizer/{k}"] = v
        if not self.frame_index:
            out = empty_output()
            out.stage_ms = stage_ms
            out.metrics = self._metrics()
            return out
        T_wk = torch.stack(opt.T_wk)
        T_wc = self._at_frame_times(frame_poses(T_wk, self.frame_kf, self.frame_T_kf))
        points, colors = self._map(T_wk)  # clouds belong to the depth instants: optimised poses as they are
        # keyframes.txt is stamped with the keyframes' colour timestamps: their re-sampled poses.
        position = {f: p for p, f in enumerate(self.frame_index)}
        kf_rows = torch.tensor([position[k.frame_index] for k in self.keyframes], dtype=torch.int64)
        return SystemOutput(
            frame_indices=torch.tensor(self.frame_index, dtype=torch.int64),
            timestamps=torch.tensor(self.frame_time, dtype=torch.float64),
            T_wc=T_wc,
            keyframe_indices=torch.tensor([k.frame_index for k in self.keyframes], dtype=torch.int64),
            keyframe_T_wc=T_wc[kf_rows],
            map_points=points,
            map_colors=colors,
            stage_ms=stage_ms,
            metrics=self._metrics(),
            prior_indices=self._prior_indices(),
        )

    def _prior_indices(self) -> Tensor:
        """Sequence indices of the frames on a motion prior: lost ones, and unlinked keyframes no pair links."""
        linked = {k for pair in self.optimizer.pairs for k in pair}
        rows = [f for f, why, kf in zip(self.frame_index, self.frame_prior, self.frame_kf)
                if why == "lost" or (why == "unlinked" and kf not in linked)]
        return torch.tensor(rows, dtype=torch.int64)

    def _at_frame_times(self, T_geom: Tensor) -> Tensor:
        """Re-sample the poses from the depth instants to the frames' (colour) timestamps.

        A registered pose belongs to the instant of the depth image that gave the 3-D points.
        Where the sequence records depth timestamps apart from the colour ones (TUM fr1: ±15 ms),
        the trajectory is interpolated (linear / SLERP) at the colour timestamps between
        neighbouring depth instants; poses outside their span or across gaps longer than
        ``interpolation_max_gap`` stay as registered.
        """
        t_geom = torch.tensor(self.frame_geom_time, dtype=torch.float64)
        t_frame = torch.tensor(self.frame_time, dtype=torch.float64)
        return resample_poses(t_geom, T_geom, t_frame, self.cfg.interpolation_max_gap)

    def _map(self, T_wk: Tensor) -> tuple[Tensor, Tensor]:
        pts = [k.map_points.cpu().double() @ T[:3, :3].T + T[:3, 3] for k, T in zip(self.keyframes, T_wk)]
        cols = [k.map_colors.cpu() for k in self.keyframes]
        return voxel_downsample(torch.cat(pts), torch.cat(cols), self.cfg.map_voxel)

    def _metrics(self) -> dict[str, Any]:
        opt = self.optimizer
        kinds = opt.pair_kind
        fastgo = opt.fastgo_ms
        return {
            "frontend": self.cfg.frontend,
            "threaded": self.cfg.threaded,
            "loops": dict(opt.loops),
            "pairs": {"odometry": kinds.count("odometry"), "loop": kinds.count("loop")},
            # Accepted loop closures as (earlier, later) sequence frame indices of their keyframes.
            "loop_frames": [[self.keyframes[i].frame_index, self.keyframes[j].frame_index]
                            for (i, j), kind in zip(opt.pairs, kinds) if kind == "loop"],
            "tracking": dict(self.counts),
            "correspondences_mean": float(torch.tensor(self.inliers, dtype=torch.float64).mean()) if self.inliers else None,
            "fastgo_ms_mean": sum(fastgo) / len(fastgo) if fastgo else None,
            "fastgo_ms_last": fastgo[-1] if fastgo else None,
            "fastgo_ms_max": max(fastgo) if fastgo else None,
        }


def track_frames(systems: list[GCSlam], frames: list[Frame], max_batch: int | None = None) -> StepReport:
    """Advance GC-SLAM systems (one per sequence, started with ``deferred=True``) by one frame each.

    Each system tracks its frame on its own (ORB, registration, keyframe decision); then the new
    keyframes of all systems are inserted together (:func:`insert_keyframes`): one FastGO call
    optimises every sequence's pose graph at once. Each system's result equals its result alone.

    Args:
        systems: started GC-SLAM systems in deferred mode.
        frames: the next frame of each system's sequence.
        max_batch: unused (every pose graph of the step shares one FastGO call); accepted so the
            lockstep driver treats both systems alike.

    Returns:
        StepReport: per system its error (its state is then undefined) and compute seconds (its
        tracking plus an equal share of the joint optimisation).
    """
    if len(frames) != len(systems):
        raise ShapeError(f"frames: expected one frame per system ({len(systems)}), got {len(frames)}")
    errors: list[Exception | None] = [None] * len(systems)
    compute = [0.0] * len(systems)
    for k, (system, frame) in enumerate(zip(systems, frames)):
        if not system.deferred:
            raise ConfigError(f"systems[{k}]: expected a GCSlam built with deferred=True")
        t0 = time.perf_counter()
        try:
            system.track(frame)
        except Exception as exc:  # noqa: BLE001 - reported in the system's place
            errors[k] = exc
        compute[k] += time.perf_counter() - t0
    ready = [k for k, s in enumerate(systems) if errors[k] is None and s._worker.pending]
    t0 = time.perf_counter()
    while ready:
        # Normally one keyframe per system and step; relocalisation never queues more than one.
        opts = [systems[k].optimizer for k in ready]
        evs = [systems[k]._worker.pending.pop(0) for k in ready]
        for k, err in zip(ready, insert_keyframes(opts, evs)):
            errors[k] = err
        ready = [k for k in ready if errors[k] is None and systems[k]._worker.pending]
    shared = time.perf_counter() - t0
    active = [k for k in range(len(systems)) if errors[k] is None]
    for k in active:
        compute[k] += shared / max(len(active), 1)
    return StepReport(errors=errors, compute_s=compute)


def _memory(cfg: GCSlamConfig, camera, batch: int) -> dict[str, tuple[int, str]]:
    """The dense front-end's working pyramid (``systems.memory``); the sparse one adds nothing."""
    if cfg.frontend != "dense":
        return {}
    factor = max(1, round(camera.width / cfg.dense.width))
    working = (camera.width // factor) * (camera.height // factor)
    return {"dense pyramid": (DENSE_BYTES_PER_WORKING_PIXEL * working * batch,
                              f"image {camera.width}x{camera.height}, dense.width = {cfg.dense.width}")}


SPEC = SystemSpec(
    name="gcslam",
    description="GC-SLAM: ORB/dense registration with FastGO global optimisation",
    config_cls=GCSlamConfig,
    build=GCSlam,
    memory=_memory,
    # Lockstep: each frame tracked on its own, the new keyframes of all sequences optimised in
    # one FastGO call (``track_frames``, with the optimisation inline instead of in a thread).
    lockstep=LockstepSpec(step=track_frames, build=functools.partial(GCSlam, deferred=True)),
)
