"""GC-SLAM: frame-to-keyframe registration, MILD loop detection and FastGO (paper §IV).

Two threads, as in the paper:

* **tracking** (the caller's thread): every frame is registered to the latest keyframe, by ORB
  features (``frontend: sparse``, :mod:`torchslam.registration.sparse`) or by dense
  photometric + geometric alignment (``frontend: dense``, :mod:`torchslam.registration.dense`).
  A frame whose keyframe's points have moved by more than ``keyframe_displacement * f`` pixels on
  average becomes a new keyframe; the correspondences of its registration become the statistics
  of the pair (previous keyframe, new keyframe). Frames keep their pose relative to their
  keyframe and are re-posed from the optimised keyframes at the end.
* **optimisation** (a background process or thread, ``background``, or inline with ``threaded: false``): for each new
  keyframe in insertion order, MILD (multi-index hashing of ORB descriptors, no trained
  vocabulary) proposes the ``top_k`` most similar earlier keyframes; they are registered to the
  new keyframe with sparse registration all at once; FastGO runs ``fastgo_iterations`` Gauss-
  Newton iterations over all keyframes (by default only where there are candidates: a keyframe
  without them adds a leaf, ``fastgo_every_keyframe``); candidate loops are kept only if the
  registration error of the earlier pairs does not rise by more than ``loop_threshold`` (5 %) after
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

Where things are: the settings in :mod:`.config`, the two front-ends (one interface, chosen
once in ``start``) in :mod:`.frontend`, the optimisation side in :mod:`.optimizer`; this module
holds the tracker, its frame bookkeeping and the lockstep steps (:func:`track_frames`,
:func:`insert_keyframes`).

Convention:
    The world is the first keyframe's camera frame (FastGO holds keyframe 0 fixed at the
    identity); trajectory, keyframes and ``map.ply`` (the keyframes' coloured depth points in
    their optimised poses) are all in it.
"""

from __future__ import annotations

import collections
import functools
import logging
import statistics
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...data.frame import Frame, Sequence
from ...data.trajectory import Trajectory
from ...errors import ConfigError, ShapeError, TorchSlamError
from ...fastgo import PairStats, optimize_batch
from ...features.matching import MatchBackend, cpu_auto_backend
from ...devices import numpy_viewable
from ...geometry import (
    PinholeCamera, backproject_depth, project_points, se3_exp, se3_exp_numpy, se3_inverse, se3_inverse_numpy, se3_log, se3_log_numpy,
    undistorted_rays,
)
from ...registration.dense import DenseFrame, dense_images
from ...registration.rolling import dense_images_at_stamp, features_at_stamp
from ...registration.sparse import FrameFeatures, SparseResult, register_sparse_batch
from ...stamps import STAMP_TOLERANCE_S
from ..base import AheadResults, StepReport, SystemOutput, add_stage_ms
from ..framelog import FrameLog, voxel_downsample
from ..memory import DENSE_PAIR_BYTES_PER_WORKING_PIXEL
from ..monitor import Monitor
from ..registry import LockstepSpec, SystemSpec
from .config import GCSlamConfig
from .frontend import PreparedFrame, Registration, TrackingFrontend, dense_working_pixels, frontend_class, make_frontend
from .optimizer import Anchor, KeyframeEvent, Optimizer, ProcessWorker, Worker, make_worker

__all__ = ["SPEC", "GCSlam", "GCSlamConfig", "insert_keyframe", "insert_keyframes", "track_frames"]

logger = logging.getLogger(__name__)

# ``dense_orb_start_residual``: the residuals compared against (the last tracked registrations),
# and how many are needed before the test runs (until then every registration is started from ORB too).
_RESIDUAL_WINDOW = 10
_RESIDUAL_MIN = 3


class _Stopwatch:
    """Per-stage wall time of one ``track`` call: each lap ends a stage and starts the next."""

    def __init__(self, stage_ms: dict[str, float]) -> None:
        self.stage_ms = stage_ms
        self.t0 = time.perf_counter()

    def lap(self, stage: str, exclude_s: float = 0.0) -> None:
        """Add the time since the last lap, less ``exclude_s`` seconds, to ``stage``."""
        self.t0 = add_stage_ms(self.stage_ms, stage, self.t0 + exclude_s)


@dataclass
class _TrackKeyframe:
    """What the tracker keeps of a keyframe (a :class:`~.frontend.RegistrationTarget`)."""

    kf: int
    frame_index: int
    features: FrameFeatures
    sample_points: Tensor  # (S, 3) float64 keyframe-frame points for the displacement test
    sample_pixels: Tensor  # (S, 2) float64 their pixels in the keyframe
    dense: DenseFrame | None  # the dense pyramid of the current keyframe only (dense front-end); None for older ones
    map_points: Tensor  # (P, 3) float32 keyframe-frame points of map.ply
    map_colors: Tensor  # (P, 3) float32
    depth: Tensor | None = None  # (1, H, W) depth of the current keyframe (sparse front-end's depth refinement); None for older ones
    # readout_time: the motion its images (dense) or ORB points (sparse) were moved to its stamp
    # with; None while as read (frames registered to it are moved only where it was)
    twist: Tensor | None = None

    @property
    def at_stamp(self) -> bool:
        return self.twist is not None


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
        self._worker: Worker | ProcessWorker | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, sequence: Sequence) -> None:
        cfg = self.cfg
        self.sequence_name = sequence.name
        self.camera: PinholeCamera = sequence.camera
        # readout_time, auto resolved: the sequence's own rolling shutter.
        self.readout, self.readout_source = cfg.readout_for(sequence)
        self.intrinsics = self.camera.as_tensor(torch.float64, self.device)[None]
        self.rays = undistorted_rays(self.camera, torch.float64, self.device) if self.camera.has_distortion else None
        # Every pixel's ray for lifting keyframe pixels (the pinhole factors without distortion,
        # exactly ``backproject_depth``'s).
        self._pixel_rays = self.rays if self.rays is not None else undistorted_rays(self.camera, torch.float64, self.device)
        self.optimizer = Optimizer(cfg, self.monitor)
        if self.device.type == "cpu" and cfg.sparse.match_backend is MatchBackend.AUTO:
            # Time the CPU's matching backends once here, before the optimisation's and the
            # frames' processes are forked, so that they inherit the choice.
            cpu_auto_backend()
        self._worker = make_worker(self.optimizer, insert_keyframe, cfg, self.device, self.deferred)
        self.keyframes: list[_TrackKeyframe] = []
        # Prior tags: "lost" (holds the last pose), "unlinked" (an unlinked keyframe started at
        # the last pose: a motion prior until a loop closure links it).
        self.frames = FrameLog()
        self.lost_in_row = 0
        self.counts = {"lost_frames": 0, "relocalized": 0, "unlinked_keyframes": 0, "no_depth": 0, "tracking_failures": 0,
                       "promoted_keyframes": 0, "orb_starts": 0, "orb_starts_kept": 0, "orb_starts_residual": 0,
                       "orb_checks": 0, "orb_starts_check": 0}
        self.inliers: list[int] = []
        self.stage_ms: dict[str, float] = {}
        self.generator = torch.Generator().manual_seed(cfg.sparse.seed)
        self._check_generator = torch.Generator().manual_seed(cfg.sparse.seed)
        self.frontend: TrackingFrontend = make_frontend(cfg, self.camera, self.rays, self.generator, self.readout)
        self._last_T_kf = torch.eye(4, dtype=torch.float64, device=self.device)
        # The last tracked step's motion (``motion_prior``): (6,) twist per second in the frame's
        # own coordinates and the time of that frame; None when the last frame was not tracked.
        self._velocity: Tensor | None = None
        self._last_time: float | None = None
        self._need_unlinked = False
        # The last frame recorded against the current keyframe (frame, view, registration) and the
        # most correspondences a frame kept to that keyframe (``keyframe_weak_ratio``).
        self._previous: tuple[Frame, PreparedFrame, Registration] | None = None
        self._best_correspondences = 0
        # The correspondences of the registration that linked the current keyframe to the one
        # before (0 where there is none: the first, unlinked or relocalised keyframes): what a
        # dense registration to a keyframe without tracked frames yet is compared with.
        self._link_correspondences = 0
        # readout_time: frames whose points were moved to their stamps, keyframes whose images were resampled so.
        self.rolling_shutter = {"frames": 0, "keyframes": 0}
        # Photometric RMS residuals of the last dense tracking registrations kept
        # (``dense_orb_start_residual``).
        self._residuals: collections.deque[float] = collections.deque(maxlen=_RESIDUAL_WINDOW)
        self._inline_s = 0.0
        # readout_time: a keyframe made with no motion yet (the first, an unlinked or relocalised
        # one) waits here for the motion of the first frame tracked against it before the
        # optimiser gets it (``_release_held``; released as read where a keyframe comes first).
        self._held: KeyframeEvent | None = None
        self.last_frame_index: int | None = None  # the frame last given to ``track`` (TensorBoard step)
        # Frames prepared by ``prepare_ahead`` (another thread) and not yet tracked:
        # (rgb, depth, enough valid depth, the prepared view or None where not enough).
        self._ahead = AheadResults()

    @property
    def prepares_ahead(self) -> bool:
        """Whether ``run_sequence`` prepares frames ahead on another thread (``cfg.prepare_ahead``)."""
        return self.cfg.prepare_ahead

    def prepare_ahead(self, frame: Frame) -> None:
        """What ``track`` does first, for a frame still to come: the images on the device, the
        valid-depth count and the front-end's preparation (ORB features or the dense pyramid).

        Reads only what ``start`` set up, so it may run on another thread while ``track`` runs;
        ``track`` of the frame picks the result up (and its stage times).
        """
        self.accept_ahead(frame, *self.ahead_payload(frame))

    @property
    def prepares_ahead_in_process(self) -> bool:
        """Whether ``run_sequence`` reads and prepares the frames in a child process
        (``cfg.prepare_ahead_in``; the CPU only, where a thread runs otherwise)."""
        return self.cfg.prepare_ahead and self.cfg.prepare_ahead_in == "process" and self.device.type == "cpu"

    def ahead_payload(self, frame: Frame) -> tuple[tuple, dict[str, float]]:
        """What :meth:`prepare_ahead` computes for ``frame``, and its stage times."""
        stage_ms: dict[str, float] = {}
        clock = _Stopwatch(stage_ms)
        rgb, depth, enough = self._images(frame)
        view = self.frontend.prepare(rgb, depth, keyframe=False, lap=clock.lap) if enough else None
        return (rgb, depth, enough, view), stage_ms

    def accept_ahead(self, frame: Frame, payload: tuple, stage_ms: dict[str, float]) -> None:
        """Keep ``frame``'s :meth:`ahead_payload` for its ``track``."""
        self._ahead.put(frame, payload, stage_ms)

    def _images(self, frame: Frame) -> tuple[Tensor, Tensor, bool]:
        # Non-blocking: from a pinned frame (``TUMSequence(pin_memory=True)``) the copy to a GPU overlaps.
        rgb = frame.rgb.to(self.device, non_blocking=True)
        depth = frame.depth.to(self.device, non_blocking=True)
        if numpy_viewable(depth):  # NumPy counts a comparison's True entries several times faster
            return rgb, depth, int(np.count_nonzero(depth.numpy() > 0)) >= self.cfg.min_valid_depth
        return rgb, depth, int((depth > 0).sum()) >= self.cfg.min_valid_depth

    def _toc(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    # ------------------------------------------------------------------ tracking
    def track(self, frame: Frame) -> None:
        """Register one frame to the current keyframe; make it a keyframe, relocalise it or record it."""
        cfg = self.cfg
        clock = _Stopwatch(self.stage_ms)
        self.last_frame_index = frame.index
        found, ahead = self._ahead.take(frame, self.stage_ms)
        if found:
            rgb, depth, enough, view = ahead
        else:
            rgb, depth, enough = self._images(frame)
            view = None
        if not enough:
            self.counts["no_depth"] += 1
            self._record_lost(frame)
            return
        unlinked = not self.keyframes or self._need_unlinked
        if view is None:
            view = self.frontend.prepare(rgb, depth, keyframe=unlinked, lap=clock.lap)
        elif unlinked:
            self._features(view, clock)
        if unlinked:
            self._velocity, self._last_time = None, frame.timestamp
            self._new_keyframe(frame, view, reference=None, T_ref=None, stats=None)
            self._need_unlinked = False
            clock.lap("keyframe_insertion", exclude_s=self._take_inline())
            return
        kf = self.keyframes[-1]
        T_pred = self._predicted_T_kf(frame.timestamp)
        if self.readout > 0 and kf.at_stamp:
            # Only against a keyframe at its stamp: one side moved and not the other is worse than neither.
            self._to_stamp(view, frame.timestamp)
        reg = self.frontend.register(kf, view, T_pred)
        clock.lap("registration")
        if self._needs_orb_start(kf, reg):
            reg = self._orb_start(kf, view, reg, clock)
        elif self._residual_outlier(kf, reg):
            self.counts["orb_starts_residual"] += 1
            reg = self._orb_start(kf, view, reg, clock, by_residual=True)
        if reg.ok and self._weak(reg):
            reg = self._promote_previous(view, T_pred, clock)
            kf = self.keyframes[-1]
        if not reg.ok:
            self.counts["tracking_failures"] += 1
            self._velocity = None
            self._previous = None
            self._relocalize(frame, view)
            clock.lap("relocalization", exclude_s=self._take_inline())
            return
        limit = cfg.keyframe_displacement * self.camera.fx
        moved = self._displacement(kf, reg.T_kf)
        if moved > limit and self._keyframe_check(kf):
            reg = self._check_against_orb(kf, view, reg, clock)
            moved = self._displacement(kf, reg.T_kf)
        self._update_velocity(reg.T_kf, frame.timestamp)
        if self.readout > 0:
            view.twist = self._velocity  # the motion at this frame, for its images if it becomes a keyframe
            if self._held is not None:
                self._release_held()  # the keyframe this frame was registered to, resampled with its motion
        self._best_correspondences = max(self._best_correspondences, reg.correspondences)
        if kf.dense is not None:
            self._residuals.append(_photometric(reg))
        self.lost_in_row = 0
        self.inliers.append(reg.correspondences)
        self.monitor.scalar("tracking/correspondences", reg.correspondences, frame.index)
        clock.lap("keyframe_decision")
        if moved > limit:
            self._features(view, clock)
            self._new_keyframe(frame, view, reference=kf.kf, T_ref=reg.T_kf, stats=reg.stats)
            self._link_correspondences = reg.correspondences
            clock.lap("keyframe_insertion", exclude_s=self._take_inline())
            return
        self._record(frame, kf.kf, reg.T_kf)
        self._previous = (frame, view, reg)

    def _features(self, view: PreparedFrame, clock: _Stopwatch) -> None:
        """Compute a frame's ORB features where it has none yet, timed as ``orb_extraction``."""
        if view.features is None:
            self.frontend.features(view)
            clock.lap("orb_extraction")

    def _weak(self, reg: Registration) -> bool:
        """Whether ``reg`` keeps fewer than ``keyframe_weak_ratio`` of the best correspondence
        count of a frame tracked to the current keyframe, with a better previous frame to promote."""
        ratio, prev = self.cfg.keyframe_weak_ratio, self._previous
        return (ratio > 0 and prev is not None and reg.correspondences < ratio * self._best_correspondences
                and prev[2].correspondences > reg.correspondences)

    def _needs_orb_start(self, kf: _TrackKeyframe, reg: Registration) -> bool:
        """Whether a dense registration is to be started again from ORB (``dense_orb_start``):
        it failed or kept fewer than ``keyframe_weak_ratio`` of the best count to this keyframe,
        or, before any frame is tracked to it, of the count of the registration that linked it."""
        best = self._best_correspondences or self._link_correspondences
        if not self.cfg.dense_orb_start or kf.dense is None or best <= 0:
            return False
        return not reg.ok or reg.correspondences < self.cfg.keyframe_weak_ratio * best

    def _residual_outlier(self, kf: _TrackKeyframe, reg: Registration) -> bool:
        """Whether a dense registration that kept its correspondences is to be started again from
        ORB because its photometric residual exceeds ``dense_orb_start_residual`` times the median
        of the last tracked ones (a wrong basin: a motion prior or last pose far from the frame),
        or because fewer than ``_RESIDUAL_MIN`` are known yet (a run's first registrations)."""
        ratio = self.cfg.dense_orb_start_residual
        if not self.cfg.dense_orb_start or ratio <= 0 or kf.dense is None or not reg.ok:
            return False
        if len(self._residuals) < _RESIDUAL_MIN:
            return True  # nothing to compare with yet (a run's first registrations): started from ORB too
        return _photometric(reg) > ratio * statistics.median(self._residuals)

    def _keyframe_check(self, kf: _TrackKeyframe) -> bool:
        """Whether a dense registration that makes its frame a keyframe is checked against ORB
        (``dense_orb_keyframe_check``)."""
        return self.cfg.dense_orb_start and self.cfg.dense_orb_keyframe_check and kf.dense is not None

    def _check_against_orb(self, kf: _TrackKeyframe, view: PreparedFrame, reg: Registration, clock: _Stopwatch) -> Registration:
        """``reg``, or where it disagrees with the frame's ORB registration to the keyframe (the
        dense pose moves the ORB inliers by more than ``sparse.inlier_threshold`` on average),
        the dense registration started again from the ORB pose if its photometric residual is lower."""
        self._features(view, clock)
        # Its own random stream: a check that agrees changes nothing downstream.
        res = register_sparse_batch([kf.features], [view.features], self.cfg.sparse, self._check_generator)
        self.counts["orb_checks"] += 1
        clock.lap("registration")
        if not bool(res.success[0]) or _inlier_shift(res, reg.T_kf) <= self.cfg.sparse.inlier_threshold:
            return reg
        self.counts["orb_starts_check"] += 1
        return self._orb_start(kf, view, reg, clock, by_residual=True, res=res)

    def _orb_start(self, kf: _TrackKeyframe, view: PreparedFrame, reg: Registration, clock: _Stopwatch,
                   by_residual: bool = False, res: SparseResult | None = None) -> Registration:
        """The dense registration again, started from the frame's ORB registration to the keyframe
        (brute-force matching, as the loops'; ``res`` where it is known already); the result with
        more correspondences is kept, or with ``by_residual`` the one with the lower photometric
        residual."""
        if res is None:
            self._features(view, clock)
            res = register_sparse_batch([kf.features], [view.features], self.cfg.sparse, self.generator)
        self.counts["orb_starts"] += 1
        again = None
        if bool(res.success[0]):
            again = self.frontend.register(kf, view, res.T_ij[0].to(torch.float64))
        clock.lap("registration")
        if again is not None and again.ok and (
            _photometric(again) < _photometric(reg) if by_residual
            else not reg.ok or again.correspondences > reg.correspondences
        ):
            self.counts["orb_starts_kept"] += 1
            return again
        return reg

    def _promote_previous(self, view: PreparedFrame, T_pred: Tensor, clock: _Stopwatch) -> Registration:
        """Make the previous tracked frame a keyframe and register the frame to it instead.

        A frame that keeps few of the keyframe's correspondences (blur, a fast turn) would, once
        the displacement rule fires, link its keyframe to the graph by a weak registration; the
        previous frame still registered well. It becomes the keyframe (linked by its own
        registration) and the frame is registered to it; where that fails, the frame goes on as
        a failed registration (relocalisation against the recent keyframes, the old one included).
        """
        prev_frame, prev_view, prev_reg = self._previous
        old = self.keyframes[-1]
        self._features(prev_view, clock)
        self._new_keyframe(prev_frame, prev_view, reference=old.kf, T_ref=prev_reg.T_kf, stats=prev_reg.stats, promote=True)
        self._link_correspondences = prev_reg.correspondences
        self.counts["promoted_keyframes"] += 1
        clock.lap("keyframe_insertion", exclude_s=self._take_inline())
        T_prev_inv = se3_inverse(prev_reg.T_kf.to(torch.float64))
        again = self.frontend.register(self.keyframes[-1], view, T_prev_inv @ T_pred.to(torch.float64))
        clock.lap("registration")
        return again

    def _to_stamp(self, view: PreparedFrame, t: float) -> None:
        """Move the view's points (dense pyramid or ORB) to the frame's stamp (``readout_time``)
        with the predicted motion: the last tracked step's twist (the motion prior's; on synthetic
        hand-held and orbit sequences with a planted 30 ms readout, tuning seeds, it did better
        than the mean of the last three steps: 0.133 against 0.185 cm, seeds 0-2 hand-held,
        dense), where the prior spans the gap to the last tracked frame."""
        v, t0 = self._velocity, self._last_time
        if v is None or t0 is None or not self._within_prior_gap(t - t0):
            return
        self.frontend.to_stamp(view, v)
        view.twist = v
        self.rolling_shutter["frames"] += 1

    def _predicted_T_kf(self, t: float) -> Tensor:
        """(4, 4) initial pose of the frame at time ``t`` in the current keyframe (``motion_prior``)."""
        v, t0 = self._velocity, self._last_time
        if self.cfg.motion_prior == "none" or v is None or t0 is None or not self._within_prior_gap(t - t0):
            return self._last_T_kf
        # Through the twist, never as the 4x4 step itself: exp puts the prediction back on SE(3),
        # whereas chaining the registered (float32-rounded, slightly non-orthonormal) step would
        # feed the deviation back frame after frame (7-Scenes dense diverged that way).
        step = v * (t - t0)
        if numpy_viewable(step) and numpy_viewable(self._last_T_kf):  # a few numbers: NumPy's cost, not torch's
            return torch.from_numpy(self._last_T_kf.numpy() @ se3_exp_numpy(step.numpy()[None])[0])
        return self._last_T_kf @ se3_exp(step)

    def _update_velocity(self, T_kf: Tensor, t: float) -> None:
        """Take the step from the last recorded frame to this tracked one (both in the current keyframe)."""
        t0 = self._last_time
        T_kf = T_kf.to(torch.float64)
        if numpy_viewable(T_kf) and numpy_viewable(self._last_T_kf):  # a few numbers: NumPy's cost, not torch's
            step = torch.from_numpy(se3_log_numpy((se3_inverse_numpy(self._last_T_kf.numpy()) @ T_kf.numpy())[None])[0])
        else:
            step = se3_log(se3_inverse(self._last_T_kf) @ T_kf)
        dt = t - t0 if t0 is not None else 0.0
        self._velocity = step / dt if self._within_prior_gap(dt) else None
        self._last_time = t

    def _within_prior_gap(self, dt: float) -> bool:
        """Whether the motion prior spans ``dt`` seconds: positive and at most ``motion_prior_max_gap``,
        to a microsecond (a stream at exactly that period, 5 Hz against 0.2 s, has gaps rounded a
        few ulps either side of it; timestamps carry microseconds at best)."""
        return 0.0 < dt <= self.cfg.motion_prior_max_gap + STAMP_TOLERANCE_S

    def _take_inline(self) -> float:
        s, self._inline_s = self._inline_s, 0.0
        return s

    def _displacement(self, kf: _TrackKeyframe, T_kf_frame: Tensor) -> float:
        """Mean pixel displacement of the keyframe's sample points seen from the frame."""
        if not len(kf.sample_points):
            return float("inf")
        T_kf_frame = T_kf_frame.to(torch.float64)
        if numpy_viewable(T_kf_frame) and numpy_viewable(kf.sample_points):
            return _displacement_numpy(kf.sample_points.numpy(), kf.sample_pixels.numpy(), T_kf_frame.numpy(), self.camera)
        T = se3_inverse(T_kf_frame)
        p = kf.sample_points @ T[:3, :3].T + T[:3, 3]
        uv, ok = project_points(p[None], self.intrinsics)
        ok = ok[0]
        if not bool(ok.any()):
            return float("inf")
        return float((uv[0][ok] - kf.sample_pixels[ok]).norm(dim=-1).mean())

    def _relocalize(self, frame: Frame, view: PreparedFrame) -> None:
        """Register a frame that failed to the recent keyframes (sparse); a match makes it a keyframe."""
        cfg = self.cfg
        recent = self.keyframes[-cfg.relocalize_keyframes:] if cfg.relocalize_keyframes else []
        if recent:
            feats = self.frontend.features(view)
            res = register_sparse_batch([k.features for k in recent], [feats] * len(recent), cfg.sparse, self.generator)
            good = res.success.nonzero().flatten()
            if len(good):
                b = int(good[torch.argmax(res.num_inliers[good])])
                self._velocity, self._last_time = None, frame.timestamp
                self.counts["relocalized"] += 1
                self.lost_in_row = 0
                self._new_keyframe(frame, view, reference=recent[b].kf, T_ref=res.T_ij[b],
                                   stats=res.stats[torch.tensor([b], device=res.stats.device)], relocalized=True)
                return
        self._record_lost(frame)
        if self.lost_in_row > cfg.max_lost:
            self._need_unlinked = True

    def _record_lost(self, frame: Frame) -> None:
        self._velocity = None
        self._previous = None  # a held frame is the last record now: nothing to promote
        self.counts["lost_frames"] += 1
        self.lost_in_row += 1
        self.frames.hold(frame, "lost")  # before the first pose there is nothing to hold

    def _record(self, frame: Frame, kf: int, T_kf: Tensor, prior: str | None = None) -> None:
        T = T_kf.to(torch.float64)
        self.frames.record(frame, kf, T, prior)
        self._last_T_kf = T

    def _points_at(self, depth: Tensor, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """float64 3-D points (P, 3) of the row-major ``pixels`` (K,) with valid depth up to
        ``max_depth``, and those pixels (P,): ``backproject_depth`` of only these pixels (their
        depths as a 1 x K image along their rays)."""
        z = depth.reshape(-1)[pixels].to(torch.float64)
        points, valid = backproject_depth(z.view(1, 1, 1, -1), self.intrinsics, rays=self._pixel_rays[pixels])
        keep = valid[0] & (points[0, :, 2] <= self.cfg.max_depth)
        return points[0][keep], pixels[keep]

    def _new_keyframe(
        self, frame: Frame, view: PreparedFrame, reference: int | None, T_ref: Tensor | None, stats: PairStats | None,
        relocalized: bool = False, promote: bool = False,
    ) -> None:
        """Make the frame keyframe ``len(keyframes)``, linked to ``reference`` by ``T_ref`` and ``stats`` (or unlinked).

        ``promote``: the frame is the last one recorded (``_promote_previous``); its record is
        rebased onto the new keyframe instead of recorded again.
        """
        cfg = self.cfg
        if self._held is not None:
            self._release_held()
        # As read; moved to its stamp below (readout_time) with the motion tracked at the frame.
        feats = view.features_as_read if view.features_as_read is not None else self.frontend.features(view)
        rgb, depth = view.rgb, view.depth
        kid = len(self.keyframes)
        H, W = depth.shape[-2:]
        idx = torch.arange(H * W, device=self.device).view(H, W)
        s = cfg.keyframe_sample_stride
        # Only the sample and map pixels are lifted (a few percent of the image).
        sample_points, sample = self._points_at(depth, idx[s // 2 :: s, s // 2 :: s].reshape(-1))
        # Their pixels as ``_displacement`` projects them (pinhole, along the undistorted rays),
        # so the displacement is exactly 0 at the keyframe's own pose even with lens distortion
        # (the raw pixel grid differs from that by pixels under strong distortion).
        pix = project_points(sample_points[None], self.intrinsics)[0][0]
        map_points, m = self._points_at(depth, idx[:: cfg.map_stride, :: cfg.map_stride].reshape(-1))
        colors = rgb.reshape(3, -1)[:, m].T.float()
        anchor = None
        if reference is None and len(self.frames):
            anchor = Anchor(self.frames.kf[-1], self.frames.T_kf[-1].cpu())
            self.counts["unlinked_keyframes"] += 1
        if self.keyframes:
            self.keyframes[-1].dense = None  # only the current keyframe is registered against densely
            self.keyframes[-1].depth = None
        self.keyframes.append(
            _TrackKeyframe(kid, frame.index, feats, sample_points, pix, view.dense, map_points.float(), colors,
                           depth if self.frontend.uses_keyframe_depth else None)
        )
        images = None
        if cfg.dense_pairs:
            # What the optimiser registers this keyframe's pairs densely with (the dense
            # front-end's pyramid has them already).
            images = view.dense.images() if view.dense is not None else dense_images(view.rgb[None], view.depth[None], self.camera, cfg.dense)
        # The pair to the reference is ORB-registered with the sparse front-end, and after a relocalisation.
        refine = images is not None and reference is not None and (relocalized or view.dense is None)
        ev = KeyframeEvent(kid, reference, None if T_ref is None else T_ref.to(torch.float64).cpu(),
                            None if stats is None else stats.to("cpu", torch.float64), feats, anchor, frame.index, promote,
                            images, refine)
        if self.readout > 0 and view.twist is None:
            self._held = ev  # no motion to move it with yet: the next frame's (_release_held)
        else:
            self._submit(ev if self.readout == 0 else self._keyframe_to_stamp(ev, view.twist))
        self.frames.link(kid, reference, T_ref)
        if promote:
            self.frames.rebase_last(kid)
            self._last_T_kf = torch.eye(4, dtype=torch.float64, device=self.device)
        else:
            self._record(frame, kid, torch.eye(4, dtype=torch.float64, device=self.device), prior="unlinked" if anchor is not None else None)
        self._previous = None
        self._best_correspondences = 0
        self._link_correspondences = 0
        self.monitor.scalar("progress/keyframes", kid + 1, frame.index)

    def _submit(self, ev: KeyframeEvent) -> None:
        t_submit = time.perf_counter()
        self._worker.submit(ev)
        if not self._worker.threaded:
            # Inline optimisation is reported under the optimiser's own stages, not the tracker's.
            self._inline_s += time.perf_counter() - t_submit

    def _release_held(self) -> None:
        """Hand the optimiser the keyframe held for a motion (``readout_time``), first moved to its
        stamp with the motion tracked since (the step to the frame after it), where there is one:
        the tracker then registers later frames, moved alike, against it, and the optimiser
        registers its pairs and loops with it."""
        ev, self._held = self._held, None
        v = self._velocity
        self._submit(ev if v is None else self._keyframe_to_stamp(ev, v))

    def _keyframe_to_stamp(self, ev: KeyframeEvent, twist: Tensor) -> KeyframeEvent:
        """Move the current keyframe ``ev.kf`` to its stamp with ``twist`` (``readout_time``) and
        return the event the optimiser gets. The dense front-end's keyframe has its working images
        resampled and its pyramid rebuilt (what tracking registers against, and its pairs'
        images); the sparse one's ORB points are moved, and its pairs' images go as read with
        their motion, resampled by the optimiser, off the tracking path."""
        kf = self.keyframes[ev.kf]
        kf.twist = twist
        self.rolling_shutter["keyframes"] += 1
        if kf.dense is not None:
            images = dense_images_at_stamp(kf.dense.images(), twist.to(kf.dense.levels[0].grey.dtype), self.readout)
            kf.dense = images.pyramid()
            return ev if ev.images is None else replace(ev, images=images)
        kf.features = features_at_stamp(kf.features, twist, self.camera.height, self.readout)
        return replace(ev, features=kf.features, images_motion=None if ev.images is None else (twist.cpu(), self.readout))

    # ------------------------------------------------------------------ monitoring
    def estimate_so_far(self) -> Trajectory | None:
        """The frames tracked so far, posed from the keyframes the optimiser has processed.

        With background optimisation, frames of keyframes still queued are left out. Poses are at
        the depth instants (not re-sampled to colour stamps until ``finish``).
        """
        self._worker.refresh()  # the optimisation process's progress so far
        T_wk = list(self.optimizer.T_wk)  # a snapshot: the thread only appends or replaces the list
        if not T_wk:
            return None
        return self.frames.so_far(torch.stack(T_wk), spread=self.cfg.spread_corrections)

    def progress_counters(self) -> dict[str, float]:
        """Keyframes, loops and lost frames so far, for TensorBoard."""
        self._worker.refresh()  # the optimisation process's progress so far
        loops = dict(self.optimizer.loops)
        return {
            "keyframes": float(len(self.keyframes)),
            "loops_accepted": float(loops["accepted"]),
            "loops_rejected": float(loops["rejected"]),
            "lost_frames": float(self.counts["lost_frames"]),
            "prior_frames": float(self.frames.n_prior()),
        }

    # ------------------------------------------------------------------ output
    def finish(self) -> SystemOutput:
        if self._worker is None:
            raise TorchSlamError("GCSlam.finish() called before start()")
        t0 = time.perf_counter()
        self._ahead.clear()  # frames prepared and never tracked (a stop before the end)
        if self._held is not None:
            self._release_held()
        self._worker.join()
        opt = self.optimizer
        opt.finish()
        self._toc("wait_optimizer", t0)
        stage_ms = dict(self.stage_ms)
        for k, v in opt.stage_ms.items():
            stage_ms[f"optimizer/{k}"] = v
        log = self.frames
        if not len(log):
            return FrameLog.empty(stage_ms, self._metrics())
        T_wk = torch.stack(opt.T_wk)
        # A registered pose belongs to the instant of the depth image that gave the 3-D points.
        # Where the sequence records depth timestamps apart from the colour ones (TUM fr1: ±15 ms),
        # the trajectory is interpolated (linear / SLERP) at the colour timestamps between
        # neighbouring depth instants; poses outside their span or across gaps longer than
        # ``interpolation_max_gap`` stay as registered.
        T_wc = log.at_frame_times(log.poses(T_wk, spread=self.cfg.spread_corrections), self.cfg.interpolation_max_gap)
        points, colors = self._map(T_wk)  # clouds belong to the depth instants: optimised poses as they are
        # keyframes.txt is stamped with the keyframes' colour timestamps: their re-sampled poses.
        position = {f: p for p, f in enumerate(log.index)}
        kf_rows = torch.tensor([position[k.frame_index] for k in self.keyframes], dtype=torch.int64)
        # On a motion prior: lost frames, and unlinked keyframes no pair links.
        linked = {k for pair in self.optimizer.pairs for k in pair}
        prior = log.prior_indices(lambda why, kf: why == "lost" or (why == "unlinked" and kf not in linked))
        return log.output(
            T_wc, [k.frame_index for k in self.keyframes], T_wc[kf_rows], points, colors, stage_ms, self._metrics(),
            prior,
        )

    def _map(self, T_wk: Tensor) -> tuple[Tensor, Tensor]:
        pts = [k.map_points.cpu().double() @ T[:3, :3].T + T[:3, 3] for k, T in zip(self.keyframes, T_wk)]
        cols = [k.map_colors.cpu() for k in self.keyframes]
        return voxel_downsample(torch.cat(pts), torch.cat(cols), self.cfg.map_voxel)

    def _metrics(self) -> dict[str, Any]:
        opt = self.optimizer
        kinds = opt.pair_kind
        fastgo = opt.fastgo_ms
        return {
            "frontend": self.cfg.frontend.value,
            "threaded": self.cfg.threaded,
            # Where the optimisation ran: "process", "thread", "inline" or "deferred" (lockstep).
            "background": self._worker.background,
            # Who matched ORB descriptors: sparse.match_backend, ``auto`` resolved on this machine.
            "match_backend": _resolved_match_backend(self.cfg.sparse.match_backend, self.device),
            "loops": dict(opt.loops),
            "pairs": {"odometry": kinds.count("odometry"), "loop": kinds.count("loop")},
            # keyframe_pairs=dense: ORB-registered pairs registered again densely, and those where that failed.
            "keyframe_pairs": self.cfg.keyframe_pairs,
            "dense_pairs": dict(opt.refined),
            # Accepted loop closures as (earlier, later) sequence frame indices of their keyframes.
            "loop_frames": [[self.keyframes[i].frame_index, self.keyframes[j].frame_index]
                            for (i, j), kind in zip(opt.pairs, kinds) if kind == "loop"],
            "tracking": dict(self.counts),
            # readout_time's rolling-shutter model: the setting, the seconds modelled and where
            # they came from, and the frames and keyframes it moved.
            "rolling_shutter": {"setting": self.cfg.readout_time, "readout_time_s": self.readout,
                                "source": self.readout_source, **self.rolling_shutter},
            # Sparse front-end: registrations that kept their guided matches and those that took
            # the brute-force result.
            "registrations": dict(getattr(self.frontend, "counts", {})),
            "correspondences_mean": float(torch.tensor(self.inliers, dtype=torch.float64).mean()) if self.inliers else None,
            "fastgo_ms_mean": sum(fastgo) / len(fastgo) if fastgo else None,
            "fastgo_ms_last": fastgo[-1] if fastgo else None,
            "fastgo_ms_max": max(fastgo) if fastgo else None,
        }


def _resolved_match_backend(backend: MatchBackend, device: torch.device) -> str:
    """The matching backend that ``backend`` runs as on ``device`` (``auto`` resolved)."""
    if backend is not MatchBackend.AUTO:
        return backend.value
    return cpu_auto_backend().value if device.type == "cpu" else MatchBackend.TORCH.value


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


def insert_keyframes(optimizers: list[Optimizer], events: list[KeyframeEvent]) -> list[Exception | None]:
    """Insert one new keyframe into each of several optimisers (one per sequence) at once.

    Each optimiser adds its keyframe and queries MILD; then ONE FastGO call (``optimize_batch``)
    runs ``fastgo_iterations`` over the pose graphs of those with loop candidates (of all with
    ``fastgo_every_keyframe``) together (each with its own damping and convergence); finally
    each closes its loops. With one optimiser this is exactly the
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
            candidates[k] = o.begin(ev)
        except Exception as exc:  # noqa: BLE001 - reported in the optimiser's place
            errors[k] = exc
    # Without loop candidates a keyframe only adds a leaf to the graph (``fastgo_every_keyframe``).
    idx = [k for k, o in enumerate(optimizers)
           if errors[k] is None and o.pairs and (candidates[k] or o.cfg.fastgo_every_keyframe)]
    groups = [idx] if idx else []
    while groups:
        group = groups.pop(0)
        t0 = time.perf_counter()
        try:
            problems = [optimizers[k].problem() for k in group]
            o0 = optimizers[group[0]]
            res = optimize_batch(problems, o0.fastgo_config(o0.cfg.fastgo_iterations))
        except Exception as exc:  # noqa: BLE001
            if len(group) == 1:
                errors[group[0]] = exc
            else:
                groups.extend([k] for k in group)
            continue
        share = 1000.0 * (time.perf_counter() - t0) / len(group)
        for j, k in enumerate(group):
            optimizers[k].optimized(res.problem(j), events[k].frame_index, share)
    for k, (o, ev) in enumerate(zip(optimizers, events)):
        if errors[k] is None and candidates[k]:
            try:
                o.close_loops(ev.kf, candidates[k], ev.frame_index)
            except Exception as exc:  # noqa: BLE001
                errors[k] = exc
    return errors


def insert_keyframe(optimizer: Optimizer, event: KeyframeEvent) -> None:
    """Insert one keyframe into one optimiser (:func:`insert_keyframes` with one); raise its error."""
    (error,) = insert_keyframes([optimizer], [event])
    if error is not None:
        raise error


def _memory(cfg: GCSlamConfig, camera: PinholeCamera, batch: int) -> dict[str, tuple[int, str]]:
    """The front-end's working memory (``systems.memory``): the dense pyramid (the sparse one adds
    nothing), and the optimiser's pyramids where pose-graph pairs are registered densely."""
    parts = frontend_class(cfg.frontend).memory(cfg, camera, batch)
    if cfg.dense_pairs:
        parts["dense keyframe pairs"] = (DENSE_PAIR_BYTES_PER_WORKING_PIXEL * dense_working_pixels(cfg, camera) * batch,
                                         f"keyframe_pairs = {cfg.keyframe_pairs}, dense.width = {cfg.dense.width}")
    return parts


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


def _inlier_shift(res: SparseResult, T_kf: Tensor) -> float:
    """Mean distance, metres, between the ORB inliers' frame points moved into the keyframe by
    ``T_kf`` (p_kf = T_kf p_frame) and by the ORB pose ``res.T_ij``: how far the two poses
    disagree where the ORB registration measured (0 for the same pose)."""
    inl = res.inliers[0]
    p = res.points_j[0][inl]
    T = T_kf.to(p.device, torch.float64)
    T_orb = res.T_ij[0].to(p.device, torch.float64)
    return float(((p @ T[:3, :3].T + T[:3, 3]) - (p @ T_orb[:3, :3].T + T_orb[:3, 3])).norm(dim=-1).mean())


def _photometric(reg: Registration) -> float:
    """A dense registration's photometric RMS residual (``DenseResult.residual_photometric``)."""
    return float(reg.result.residual_photometric[0])


def _displacement_numpy(points: np.ndarray, pixels: np.ndarray, T_kf_frame: np.ndarray, camera: PinholeCamera) -> float:
    """:meth:`GCSlam._displacement` in NumPy: the mean pixel distance between the keyframe's
    sample pixels and their points projected into the frame (inf when none lies in front, i.e.
    beyond ``project_points``' default ``min_depth``)."""
    T = se3_inverse_numpy(T_kf_frame)
    p = points @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    ok = z > 1e-6
    if not ok.any():
        return float("inf")
    u = camera.fx * p[ok, 0] / z[ok] + camera.cx
    v = camera.fy * p[ok, 1] / z[ok] + camera.cy
    return float(np.hypot(u - pixels[ok, 0], v - pixels[ok, 1]).mean())
