"""NI-SLAM: non-iterative RGB-D-inertial SLAM with kernel cross-correlators.

Per frame (NI-SLAM §4–§8), with no iterative optimisation in the front-end:

1. attitude ``R_wi`` from the attitude stream (IMU/AHRS, simulated gyro, or ground truth;
   ``attitude``), with the back-end's correction applied, sampled at the depth image's timestamp
   where the sequence records one (``Frame.depth_timestamp``; TUM fr1 pairs colour and depth
   ±15 ms apart);
2. the depth image becomes a point cloud, its grey values taken where the points appear in the
   colour image after the attitude's rotation between the two stamps (``sample_grey``), rotated
   into the keyframe's attitude and projected orthographically at the keyframe's resolution
   ``r_k``, the image centred on the constant-velocity prediction of the frame's translation
   (``center_on_prediction``; the paper centres it on the frame's axis);
3. the kernel cross-correlator trained on the keyframe gives the image shift and its PSR;
   well-matched pixels give the depth shift (``kcc.track_step``); the scene content moved by
   ``t = (t_xy, t_z)`` in the keyframe attitude frame, so the camera sits at ``-t``;
4. the keyframe policy (``policy.KeyframePolicy``) decides: PSR < T_K makes a new keyframe,
   PSR > T_M fuses the frame into the keyframe (moving average, Eq. (23)).

Keyframes are remembered by their ORB descriptors in a multi-index hash (no downloaded
vocabulary). A new keyframe queries it, and the keyframe nearest to it in the pose graph joins
the candidates (``loop.proximity_candidates``); each candidate is verified by correlating the new
keyframe's cloud against the candidate's fused orthographic map (PSR and a plausible relative
transform), and an accepted loop adds an edge to the SE(3) pose graph, which is optimised
with Levenberg-Marquardt. A loop is accepted only when the graph agrees with it: the chi-square
increase of the optimised graph it causes, with the edges' covariances (translation: the
correlation's Eq. (19) variance and the depth variance; rotation: the attitude source's error,
growing with the time between keyframes; with ``loop.acceptance_covariance`` "jitter" the test
takes odometry covariances from the jitter of the frames tracked against each keyframe instead,
and the graph is still optimised with the paper's), stays within a chi-square quantile
(``backend.edge_consistency``); otherwise it is rolled back (the paper's false relocalisation
check, §9.2, as a statistical test). An optional extra guard rejects a loop whose optimised graph
bends an odometry edge by more than a distance (``loop.max_odometry_bend_m``, off by default).
Optionally (``loop.local_window``) a new keyframe is also matched against a few recent
keyframes; each such edge passes the same test on the window's graph, which is then optimised. The optimised rotation of the newest keyframe
corrects the attitude stream from then on, so inertial yaw drift is fused with the back-end.

Every frame keeps its pose relative to its keyframe and is re-posed after each optimisation.
Tracked poses belong to the depth instants; the reported trajectory is interpolated from them
at the frames' (colour) timestamps.

A ``NISlam`` instance runs one sequence. Its per-frame work is split into the public phases
``prepare``, ``start_match`` and ``apply_match`` so that several instances can advance together
(``step.track_frames``, driven by ``systems.lockstep``; the phase table is in ``step``).
``NISlam.track`` is the same with one sequence.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from ...backend import edge_consistency, edge_residuals, optimize_pose_graph
from ...data.frame import Frame, Sequence
from ...data.trajectory import Trajectory
from ...features import ORBConfig, extract_orb
from ...geometry import se3_from_Rt, se3_inverse, so3_log, undistorted_rays
from ...imu.compensation import AccelerationCompensation
from ...kcc import (
    KCCFilter,
    KeyframeMap,
    TrackResult,
    TrackSummary,
    choose_resolution,
    correlator_for,
    fuse_keyframe,
    keyframe_filter,
    keyframe_map,
    orthographic_project,
    refine_against_map,
    summarize,
    track_step,
)
from ...loop import MILDConfig, MILDDatabase
from ...optim import LMConfig
from ..base import AheadResults, SystemOutput, add_stage_ms
from ..framelog import FrameLog, voxel_downsample
from ..memory import NISLAM_BYTES_PER_ORTHO_PIXEL
from ..monitor import Monitor
from ..registry import LockstepSpec, SystemSpec
from .attitude import attitude_stream
from .config import AcceptanceCovariance, NISlamConfig
from .policy import Action, KeyframePolicy
from .step import CameraRig, Cloud, FrameInput, MatchRequest, backproject, track_frames

__all__ = ["CPU_BATCH_PIXELS", "SPEC", "NISlam"]

logger = logging.getLogger(__name__)

# Every n-th valid point of a new keyframe's cloud gives its median depth (the attitude's share in
# ``_information``).
_DEPTH_SAMPLE_STEP = 16


@dataclass
class _Keyframe:
    frame_index: int
    timestamp: float
    T_wk: Tensor  # (4, 4) float64, current estimate
    R_att: Tensor  # (3, 3) float64 attitude-stream rotation at creation (before correction)
    resolution: Tensor  # (1,)
    map: KeyframeMap  # B = 1
    filter: KCCFilter | None
    cloud: Cloud | None  # cloud for loop verification (dropped after use)
    colour: Tensor | None = None  # (3, H, W) uint8 orthographic colour image at creation, on the CPU (map.ply)
    colour_valid: Tensor | None = None  # (H, W) bool, the pixels ``colour`` holds
    depth: float = 0.0  # median depth of its cloud, metres (``_information``'s attitude term)


@dataclass(frozen=True)
class _Placed:
    """A frame with its pose: what a keyframe is made from, and the last well-tracked frame.

    Attributes:
        input: the frame (phase 1).
        cloud: its cloud.
        T_wi: (4, 4) float64 pose at the depth instant.
        variance: (3,) variance of its match's translation, m^2 (None for the first keyframe).
    """

    input: FrameInput
    cloud: Cloud
    T_wi: Tensor
    variance: Tensor | None


@dataclass(frozen=True)
class _LoopEdge:
    """A verified loop candidate: keyframe ``candidate`` sees the new keyframe at ``T_jk``."""

    candidate: int
    T_jk: Tensor  # (4, 4) float64
    variance: Tensor  # (3,) m^2
    psr: float
    # (3, 3) covariance of the edge's rotation (a right perturbation, the new keyframe's axes), rad^2,
    # where it was measured (``loop.visual_rotation``); None: the attitude's rotation, no information.
    rotation_cov: Tensor | None = None


def _content_center(T_wk: Tensor, p_w: Tensor, like: Tensor) -> Tensor:
    """(1, 2) ``track_step`` centre for a camera at world position ``p_w`` matched against a keyframe at ``T_wk``.

    The camera sits at ``-t_content`` in the keyframe's attitude frame, so the content moved by
    ``R_wk^T (p_k - p_w)``; its image-plane part, in ``like``'s device and dtype.
    """
    t = T_wk[:3, :3].T @ (T_wk[:3, 3] - p_w)
    return t[None, :2].to(like.device, like.dtype)


class NISlam:
    """NI-SLAM on one sequence; see the module docstring."""

    name = "nislam"

    def __init__(self, cfg: NISlamConfig | None = None, device: str | torch.device = "cpu", monitor: Monitor | None = None):
        self.cfg = cfg or NISlamConfig()
        self.device = torch.device(device)
        self.monitor = monitor or Monitor()
        self.policy = KeyframePolicy.of(self.cfg)
        self.correlator = correlator_for(self.cfg.kcc).to(self.device)

    # ------------------------------------------------------------------ lifecycle
    def start(self, sequence: Sequence) -> None:
        cfg = self.cfg
        self.sequence_name = sequence.name
        cam = sequence.camera
        s = cfg.pixel_stride
        cam_s = cam if s == 1 else type(cam)(cam.fx / s, cam.fy / s, cam.cx / s, cam.cy / s, max(1, cam.width // s), max(1, cam.height // s))
        # Undistorted rays of the (strided) pixels: those of the full image at the kept pixels.
        # Systems whose cameras agree share the rays and the lens: one back-projection call.
        has_lens = cfg.undistort and cam.has_distortion
        self.camera = CameraRig(
            intrinsics=cam_s.as_tensor(torch.float32, self.device)[None],
            rays=undistorted_rays(cam, torch.float32, self.device, step=s) if has_lens else None,
            distortion=cam.distortion if has_lens else None,
            lens_key=(cam, s) if has_lens else None,
        )
        self.attitude = attitude_stream(sequence, cfg)
        # The filter's tilt correction run again with the tracked acceleration removed (imu and
        # simulated attitude; ground truth has no filter to run again).
        self.accel = (
            AccelerationCompensation(self.attitude, cfg.accel_window)
            if cfg.accel_compensation and self.attitude.tilt is not None else None
        )
        self.R_corr = torch.eye(3, dtype=torch.float64)
        self.keyframes: list[_Keyframe] = []
        # Prior tag "velocity": the frame's position is the constant-velocity prediction.
        self.frames = FrameLog()
        self.edges_i: list[int] = []
        self.edges_j: list[int] = []
        self.edges_T: list[Tensor] = []
        self.edges_info: list[Tensor] = []  # the optimisation's (the paper's covariances)
        self.edges_test_info: list[Tensor] = []  # the loop test's (``loop.acceptance_covariance``)
        self.edges_loop: list[bool] = []
        self.psr: list[float] = []
        self.untracked: dict[str, int] = {"attitude_gap": 0, "too_few_points": 0}
        # rejected_by_chi2: the graph disagrees with the loop (statistical test);
        # rejected_by_odometry: the optional bend guard, or a non-finite optimisation.
        self.loops = {
            "candidates": 0, "proximity_candidates": 0, "verified": 0, "accepted": 0, "rejected_by_chi2": 0,
            "rejected_by_odometry": 0,
        }
        self.loop_tests: list[dict[str, float]] = []
        # Edges to the recent keyframes (``loop.local_window``).
        self.local = {"verified": 0, "accepted": 0, "rejected_by_chi2": 0, "rejected_by_odometry": 0}
        # Verified loops whose pose was refined over the old keyframe's map (``loop.visual_rotation``).
        self.visual_rotation = {"refined": 0, "not_converged": 0, "max_change_deg": 0.0}
        # Odometry edges by the source of their translation variance in the loop test
        # (``loop.acceptance_covariance``).
        self.odometry_variances = {"jitter": 0, "eq19": 0}
        self.fused = 0
        self.stage_ms: dict[str, float] = {}
        self.mild = MILDDatabase(MILDConfig(top_k=cfg.loop.top_k, exclude_recent=cfg.loop.min_separation, min_score=cfg.loop.min_score))
        self.orb_cfg = ORBConfig(n_features=cfg.loop.orb_features)
        self.posegraph_ms: list[float] = []
        self._well_tracked: _Placed | None = None  # the last well-tracked frame since the current keyframe
        self.motion_prior_frames = 0
        self._history_start = 0
        # The velocity the prediction used when an accepted loop restarted the history, rotated with
        # the correction: it predicts the first two frames after the loop (``_predicted_position``).
        self._carried_velocity: Tensor | None = None
        self.last_frame_index: int | None = None  # the frame last given to ``track`` (TensorBoard step)
        self._response_keyframe: int | None = None  # keyframe whose first match's response is to be logged
        # Frames done by ``prepare_ahead`` (another thread) and not yet tracked: each one's input
        # with its cloud, or None at an attitude gap.
        self._ahead = AheadResults()

    def _tic(self) -> float:
        return time.perf_counter()

    def _toc(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    # ------------------------------------------------------------------ tracking
    def track(self, frame: Frame) -> None:
        """Process one frame: the B = 1 case of ``track_frames``.

        Raises:
            Whatever one of the frame's phases raised.
        """
        error = track_frames([self], [frame]).errors[0]
        if error is not None:
            raise error

    # The phases of one frame, in the order ``step.track_frames`` calls them (see ``step``).
    def prepare(self, frame: Frame) -> FrameInput | None:
        """Phase 1: the attitude at the depth and colour instants and the images on the device
        (with the back-projection, where ``prepare_ahead`` did both for this frame).

        Returns:
            The frame's input, or None when the attitude stream has a gap at the frame (counted,
            not tracked).
        """
        self.last_frame_index = frame.index
        found, input = self._ahead.take(frame, self.stage_ms)
        if not found:
            input = self._frame_input(frame)
        if input is None:
            self.untracked["attitude_gap"] += 1
        return input

    @property
    def prepares_ahead(self) -> bool:
        """Whether ``run_sequence`` prepares frames ahead on another thread (``cfg.prepare_ahead``)."""
        return self.cfg.prepare_ahead

    def prepare_ahead(self, frame: Frame) -> None:
        """Phase 1 and the back-projection of a frame still to come, for ``prepare`` to pick up.

        Reads only what ``start`` set up (camera, attitude stream), so it may run on another
        thread while the frames before are tracked; the cloud is ``backproject`` of the frame
        alone, as the step computes it.
        """
        self.accept_ahead(frame, *self.ahead_payload(frame))

    @property
    def prepares_ahead_in_process(self) -> bool:
        """Whether ``run_sequence`` reads and prepares the frames in a child process
        (``cfg.prepare_ahead_in``; the CPU only, where a thread runs otherwise)."""
        return self.cfg.prepare_ahead and self.cfg.prepare_ahead_in == "process" and self.device.type == "cpu"

    def ahead_payload(self, frame: Frame) -> tuple[FrameInput | None, dict[str, float]]:
        """What :meth:`prepare_ahead` computes for ``frame``, and its stage times."""
        t0 = time.perf_counter()
        input = self._frame_input(frame)
        if input is not None:
            # Without the camera, which ``accept_ahead`` puts back: from a child process it would
            # travel with every frame, with its cached rays (2.5 MB a frame at 640x480).
            input = replace(input, cloud=backproject([input])[0], camera=None)
        return input, {"backproject": 1000.0 * (time.perf_counter() - t0)}

    def accept_ahead(self, frame: Frame, payload: FrameInput | None, stage_ms: dict[str, float]) -> None:
        """Keep ``frame``'s :meth:`ahead_payload` for its ``prepare`` (with the system's camera)."""
        if payload is not None:
            payload = replace(payload, camera=self.camera)
        self._ahead.put(frame, payload, stage_ms)

    def _frame_input(self, frame: Frame) -> FrameInput | None:
        """The attitude at the frame's two instants and its images on the device; None at a gap."""
        cfg = self.cfg
        # Sampled at the depth image's instant (the geometry) and at the colour image's.
        times = torch.tensor([frame.geometry_time, frame.timestamp], dtype=torch.float64)
        R_att, ok = self.attitude.at(times + cfg.attitude_time_offset, cfg.attitude_max_gap)
        if not bool(ok[0]):
            return None
        # Non-blocking: from a pinned frame (``TUMSequence(pin_memory=True)``) the copy to a GPU overlaps.
        rgb = frame.rgb.to(self.device, non_blocking=True)[None]
        depth = frame.depth.to(self.device, non_blocking=True)[None]
        if cfg.pixel_stride > 1:
            rgb = rgb[..., :: cfg.pixel_stride, :: cfg.pixel_stride]
            depth = depth[..., :: cfg.pixel_stride, :: cfg.pixel_stride]
        resample = cfg.grey_at_depth_time and bool(ok[1]) and float(times[0]) != float(times[1])
        return FrameInput(frame=frame, times=times, R_att=R_att, rgb=rgb, depth=depth, camera=self.camera, resample_grey=resample)

    def start_match(self, input: FrameInput, cloud: Cloud) -> MatchRequest | None:
        """Phase 2, after back-projection: too few points, or the first keyframe; else what to match.

        Returns:
            The match against the current keyframe, or None when the frame is not matched.
        """
        if cloud.n_valid < self.cfg.min_valid_points:
            self.untracked["too_few_points"] += 1
            return None
        if self.accel is not None:
            # The same world-frame correction at both instants: their relative rotation (the grey
            # re-sampling's) is unchanged.
            C = self.accel.correction(float(input.times[0]) + self.cfg.attitude_time_offset)
            input = replace(input, R_att=C.to(input.R_att.device, input.R_att.dtype) @ input.R_att)
        R_wi = self.R_corr @ input.R_att[0]
        if not self.keyframes:
            first = _Placed(input, cloud, se3_from_Rt(R_wi, torch.zeros(3, dtype=torch.float64)), None)
            self._new_keyframe(first)
            self._record(input.frame, first.T_wi)
            self.psr.append(math.inf)
            self._well_tracked = None
            return None
        return self._request(input, cloud, R_wi, retried=False)

    def apply_match(
        self, request: MatchRequest, res: TrackResult, kf_filter: KCCFilter, summary: TrackSummary
    ) -> MatchRequest | None:
        """Phase 3: the match against the keyframe, judged by the keyframe policy.

        Args:
            request: the match asked for (``start_match`` or a retry).
            res: its result (B = 1), on the device.
            kf_filter: the keyframe's filter as the scheduler holds it (a row of its batch).
            summary: the result's host-side numbers (read back by the scheduler for its whole
                batch at once): every decision and pose here uses them, so nothing waits for
                the device.

        Returns:
            The retry (against a keyframe made from the last well-tracked frame) when the match
            is lost and a retry is possible; else None: the frame is concluded.
        """
        self.keyframes[-1].filter = kf_filter
        T_wi = self._pose(summary.t_content, request.R_wi)
        can_retry = not request.retried and self._well_tracked is not None
        psr = summary.psr
        verdict = self.policy.decide(psr, summary.depth_ok, T_wi[:3, 3], request.p_pred, can_retry, request.check_jump)
        if verdict.action is Action.RETRY:
            # The frame matches its keyframe poorly. Its own estimate is the least reliable one,
            # so the last well-tracked frame becomes the keyframe and this frame is matched again.
            self._new_keyframe(self._well_tracked, previous=self.keyframes[-1])
            self._rebase_last_frame()
            # A loop closed at that keyframe may have corrected the attitude: apply it.
            return self._request(request.input, request.cloud, self.R_corr @ request.input.R_att[0], retried=True)
        self.psr.append(psr)
        step = request.input.frame.index
        self.monitor.scalar("tracking/psr", psr, step)
        if self._response_keyframe == len(self.keyframes) - 1:
            # The correlation response of the first frame matched against an imaged keyframe,
            # zero shift at the centre.
            g = torch.fft.fftshift(res.response[0].detach().float(), dim=(-2, -1))
            self.monitor.image("keyframe/response", ((g - g.min()) / (g.max() - g.min()).clamp_min(1e-12))[None], step)
            self._response_keyframe = None
        kf = self.keyframes[-1]
        if verdict.action is Action.NEW_KEYFRAME:
            if verdict.use_prior:
                # The frame's correlation estimate is not to be trusted: its position is the
                # constant-velocity prediction.
                T_wi = se3_from_Rt(request.R_wi, request.p_pred)
                self.motion_prior_frames += 1
            # Nothing better to match against: the frame starts a keyframe of its own.
            self._new_keyframe(_Placed(request.input, request.cloud, T_wi, summary.variance), previous=kf)
            self._well_tracked = None
        else:
            if verdict.fuse:
                # The filter stays the one trained when the keyframe was created: the paper
                # trains only on new keyframes, and retraining per fused frame would double the
                # frame cost. Fusion runs per sequence: on B = 1 its integer shifts are slice
                # copies, cheaper per frame than the batched gather.
                t0 = self._tic()
                kf.map = fuse_keyframe(kf.map, res.frame, summary.index, res.t_content[:, 2], res.matched, res.psr, self.policy.T_M)
                self.fused += 1
                self._toc("fusion", t0)
            self._well_tracked = _Placed(request.input, request.cloud, T_wi, summary.variance)
        self._record(request.input.frame, T_wi, prior=verdict.use_prior)
        return None

    def _request(self, input: FrameInput, cloud: Cloud, R_wi: Tensor, retried: bool) -> MatchRequest:
        """The match of a frame against the current keyframe, with its predicted position."""
        kf = self.keyframes[-1]
        p_pred = self._predicted_position(input.frame.timestamp)
        center = None
        if p_pred is not None and self.cfg.center_on_prediction:
            center = _content_center(kf.T_wk, p_pred, cloud.points)
        return MatchRequest(
            input=input, cloud=cloud, R_wi=R_wi, p_pred=p_pred,
            R_kf_frame=(kf.T_wk[:3, :3].T @ R_wi)[None], kf_map=kf.map, kf_filter=self._ensure_filter(kf),
            resolution=kf.resolution, correlator=self.correlator, retried=retried, center=center,
            check_jump=self._prediction_measured(),
        )

    def _prediction_measured(self) -> bool:
        """Whether the two frames the constant-velocity prediction comes from were both measured,
        not placed on the motion prior (``_predicted_position``)."""
        prior = self.frames.prior
        return all(p is None for p in prior[max(self._history_start, len(prior) - 2):])

    def _pose(self, t_content: Tensor, R_wi: Tensor) -> Tensor:
        """(4, 4) pose of a frame matched against the current keyframe, from its (3,) host ``t_content``."""
        kf = self.keyframes[-1]
        R_wk = kf.T_wk[:3, :3]
        # The scene content moved by t, so the camera sits at -t in the keyframe attitude frame.
        p_k = -t_content.to(torch.float64)
        return se3_from_Rt(R_wi, kf.T_wk[:3, 3] + R_wk @ p_k)

    def _predicted_position(self, t: float) -> Tensor | None:
        """Constant-velocity prediction from the last recorded frame (None before two frames).

        A loop correction moves keyframes by different amounts, so velocities straddling one are
        meaningless: the history restarts after every accepted loop, and until two frames are
        recorded after it, the velocity from before the loop (``_carried_velocity``) carries the
        prediction from the last recorded frame's corrected position.
        """
        log = self.frames
        if not len(log):
            return None
        v = self._velocity()
        if v is None:
            return None
        return self._world_positions(1)[0] + v * (t - log.time[-1])

    def _velocity(self) -> Tensor | None:
        """(3,) float64 world velocity of the prediction, m/s: from the last two recorded frames
        since the history restarted, else the one carried across the latest loop (or None)."""
        log = self.frames
        if len(log) - self._history_start < 2:
            return self._carried_velocity
        p = self._world_positions(2)
        t1, t2 = log.time[-2], log.time[-1]
        if not t2 > t1:
            return torch.zeros(3, dtype=p.dtype)
        return (p[1] - p[0]) / (t2 - t1)

    def _world_positions(self, n: int) -> Tensor:
        """(n, 3) float64 world positions of the ``n`` newest recorded frames, oldest first, at
        their keyframes' current poses (each ``T_wk[kf] @ T_kf``)."""
        log = self.frames
        if not n:
            return torch.zeros(0, 3, dtype=torch.float64)
        return torch.stack([(self.keyframes[log.kf[m]].T_wk @ log.T_kf[m])[:3, 3] for m in range(len(log) - n, len(log))])

    def _rebase_last_frame(self) -> None:
        """The newest recorded frame became a keyframe: express it relative to itself."""
        self.frames.rebase_last(len(self.keyframes) - 1)
        self._well_tracked = None

    def _record(self, frame: Frame, T_wi: Tensor, prior: bool = False) -> None:
        """Log the frame at world pose ``T_wi`` (4, 4), relative to the current keyframe."""
        kf = self.keyframes[-1]
        self.frames.record(frame, len(self.keyframes) - 1, se3_inverse(kf.T_wk) @ T_wi, "velocity" if prior else None)
        if self.accel is not None:
            self.accel.observe(frame.geometry_time + self.cfg.attitude_time_offset, T_wi[:3, 3])

    def _ensure_filter(self, kf: _Keyframe) -> KCCFilter:
        if kf.filter is None:
            kf.filter = keyframe_filter(kf.map, self.correlator)
        return kf.filter

    def _new_keyframe(self, src: _Placed, previous: _Keyframe | None = None) -> None:
        """Make ``src`` the current keyframe: its map, filter, odometry edge and loop closure."""
        cfg = self.cfg
        t0 = self._tic()
        k = cfg.kcc
        frame, T_wi, rgb = src.input.frame, src.T_wi, src.input.rgb
        points, grey, valid = src.cloud.points, src.cloud.grey, src.cloud.valid
        size = (k.ortho_height, k.ortho_width)
        r = choose_resolution(points, valid, size, k.coverage, k.sample_step)
        # The keyframe's colour rendered with its grey (same z-buffer winners), for the colours
        # of map.ply; the tracking itself works on grey.
        n = points.shape[1]
        ortho = orthographic_project(points, grey, valid, None, r, size, colour=rgb.reshape(1, 3, n))
        kf = _Keyframe(frame.index, frame.timestamp, T_wi, src.input.R_att[0], r, keyframe_map(ortho), None, src.cloud)
        z = points[0, :, 2][valid[0]][::_DEPTH_SAMPLE_STEP]
        kf.depth = float(z.median()) if len(z) else 0.0
        kf.colour = (ortho.colour[0].clamp(0, 1) * 255).round().to(torch.uint8).cpu()
        kf.colour_valid = ortho.valid[0].cpu()
        if previous is not None:
            # The previous keyframe's filter (possibly a row of a batch, ``track_frames``) is no
            # longer needed for tracking.
            previous.filter = None
        self.keyframes.append(kf)
        self._ensure_filter(kf)
        kid = len(self.keyframes) - 1
        if previous is not None:
            dt = kf.timestamp - previous.timestamp
            T_ij = se3_inverse(previous.T_wk) @ T_wi
            info = test_info = self._information(T_ij, src.variance, dt, 0.0, loop=False)
            jitter = self._jitter_variance(kid - 1) if self._jitter_test else None
            self.odometry_variances["jitter" if jitter is not None else "eq19"] += 1
            if self._jitter_test:
                # The jitter is calibrated already; without it, the match's Eq. (19) variance.
                variance, scaled = (src.variance, True) if jitter is None else (jitter, False)
                test_info = self._information(T_ij, variance, dt, kf.depth, loop=False, scaled=scaled)
            self._add_edge(kid - 1, kid, T_ij, info, test_info)
        t0 = self._toc("keyframe", t0)
        self.monitor.scalar("progress/keyframes", len(self.keyframes), frame.index)
        if cfg.monitor_images_every and kid % cfg.monitor_images_every == 0:
            self.monitor.image("keyframe/ortho_grey", ortho.grey[0][None], frame.index)
            self._response_keyframe = kid
        if cfg.loop.enabled:
            if cfg.loop.local_window:
                self._local_window(kid)
            self._loop_closure(kid, rgb)
            self._toc("loop", t0)
        kf.cloud = None

    @property
    def _jitter_test(self) -> bool:
        """Whether the loop test takes the jitter covariances (``loop.acceptance_covariance``)."""
        return self.cfg.loop.acceptance_covariance is AcceptanceCovariance.JITTER

    def _drift_variance(self, j: int, k: int) -> float:
        """Variance per axis of the odometry's common drift between keyframes ``j`` and ``k``, m^2.

        ``(loop.drift_per_metre L)^2``, ``L`` the path along the keyframe chain between them (the
        graph's current poses); 0 unless ``loop.acceptance_covariance`` is "jitter". The jitter
        covariances of the odometry edges are independent, so over a chain they grow with the
        square root of its length, while a drift common to the edges (a scale error, a slow turn)
        grows with the length itself. The loop test allows for it (``_try_loop``); the graph is
        then optimised without it, since it is not the loop's error.
        """
        lc = self.cfg.loop
        lo, hi = min(j, k), max(j, k)
        if not self._jitter_test or lc.drift_per_metre == 0.0 or hi - lo < 2:
            return 0.0
        p = torch.stack([kf.T_wk[:3, 3] for kf in self.keyframes[lo : hi + 1]])
        return (lc.drift_per_metre * float((p[1:] - p[:-1]).norm(dim=1).sum())) ** 2

    def _jitter_variance(self, k: int) -> Tensor | None:
        """(3,) float64 translation variance of keyframe ``k``'s odometry edge from its frames' jitter, m^2.

        ``loop.jitter_variance_scale`` times the mean square second difference of the positions
        of the frames tracked against keyframe ``k`` (the newest run of the log; frames placed by
        a motion prior left out) over 6, per axis of the keyframe's frame; None with fewer than
        ``loop.min_jitter_frames`` such frames. Runs once per keyframe. (The attitude's share,
        which consecutive frames do not show, is added by ``_information``.)
        """
        lc, log = self.cfg.loop, self.frames
        start = len(log)
        while start > 0 and log.kf[start - 1] == k:
            start -= 1
        rows = [m for m in range(start, len(log)) if log.prior[m] is None]
        if len(rows) < lc.min_jitter_frames:
            return None
        p = torch.stack([log.T_kf[m][:3, 3] for m in rows]).to(torch.float64)
        d2 = p[2:] - 2.0 * p[1:-1] + p[:-2]
        return lc.jitter_variance_scale * d2.square().mean(dim=0) / 6.0

    def _information(
        self, T_ij: Tensor, variance: Tensor | None, dt: float, depth: float, loop: bool, scaled: bool = True, extra: float = 0.0,
        rotation_cov: Tensor | None = None,
    ) -> Tensor:
        """(6, 6) information of edge ``T_ij`` (4, 4) from its translation variance (3,) m^2.

        The variance is per axis of node i's frame, where the match measured the translation; the
        residual's translation is in node j's (``log(T_ij^-1 T_wi^-1 T_wj)``), so the translation
        block is rotated by ``R_ij``.

        Translation: a match's Eq. (19) variance (x, y) and depth variance (z), each scaled
        (``loop.translation_variance_scale``, ``loop.depth_variance_scale``; ``scaled=False``: a
        variance already calibrated, ``_jitter_variance``), plus the attitude's share, then
        floored. The attitude's error between the two keyframes, ``dt`` seconds apart
        (``_rotation_variance``), turns the orthographic image the match was made in, and so
        shifts its content across the image plane by about the scene's ``depth`` (metres) times
        the angle: ``depth^2 σ_r^2`` is added to x and y. Consecutive frames share the attitude's
        slow drift, so their jitter does not show it; over a loop's span it is the largest term
        with an inertial attitude. ``extra`` (m^2) is added to every axis (``_drift_variance``).
        Rotation: for odometry, the attitude source's error between keyframes ``dt`` seconds
        apart (``LoopConfig``); a loop edge carries none, since its rotation is the attitude's
        own estimate, already in the graph through the odometry edges, unless its rotation was
        measured (``rotation_cov``, (3, 3) rad^2, ``loop.visual_rotation``): then its inverse, and
        that rotation's variance (the mean of its diagonal) replaces the attitude's in the shift.
        """
        lc = self.cfg.loop
        if variance is None:
            variance = torch.full((3,), math.inf, dtype=torch.float64)
        scale = torch.tensor([lc.translation_variance_scale, lc.translation_variance_scale, lc.depth_variance_scale], dtype=torch.float64)
        var_r = self._rotation_variance(dt) if rotation_cov is None else float(rotation_cov.diagonal().mean())
        shift = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64) * depth**2 * var_r
        var_t = (variance.to(torch.float64) * (scale if scaled else 1.0) + shift + extra).nan_to_num(nan=1.0, posinf=1.0).clamp(lc.min_translation_sigma_m**2, 1.0)
        R = T_ij[:3, :3].to(torch.float64)
        info_t = R.T @ torch.diag(1.0 / var_t) @ R
        if loop and rotation_cov is not None:
            info_r = torch.linalg.inv(rotation_cov.to(torch.float64))
        elif loop:
            info_r = torch.zeros(3, 3, dtype=torch.float64)
        else:
            info_r = torch.eye(3, dtype=torch.float64) / self._rotation_variance(dt)
        return torch.block_diag(info_t, info_r)

    def _rotation_variance(self, dt: float) -> float:
        """Per-axis variance of the attitude's relative rotation over ``dt`` seconds, rad^2."""
        lc, cfg = self.cfg.loop, self.cfg
        if self.attitude.source == "groundtruth":
            return math.radians(lc.groundtruth_rotation_sigma_deg) ** 2
        dt = abs(dt)
        drift = (lc.gyro_bias_sigma * dt) ** 2 + cfg.sim_gyro_noise**2 * dt + cfg.sim_bias_walk**2 * dt**3 / 3
        return math.radians(lc.rotation_sigma_deg) ** 2 + min(drift, math.radians(lc.max_drift_deg) ** 2)

    def _add_edge(self, i: int, j: int, T_ij: Tensor, information: Tensor, test_information: Tensor | None = None, loop: bool = False) -> None:
        """Append an edge with its optimisation information and its loop test's (None: the same)."""
        self.edges_i.append(i)
        self.edges_j.append(j)
        self.edges_T.append(T_ij.to(torch.float64))
        self.edges_info.append(information)
        self.edges_test_info.append(information if test_information is None else test_information)
        self.edges_loop.append(loop)

    # ------------------------------------------------------------------ loop closure
    def _loop_closure(self, kid: int, rgb: Tensor) -> None:
        cfg = self.cfg
        kf = self.keyframes[kid]
        feats = extract_orb(rgb[0].float().cpu(), self.orb_cfg)
        desc = feats.descriptors
        if len(desc) == 0:
            return
        ids, _ = self.mild.query(desc) if len(self.mild) else (torch.zeros(0, dtype=torch.int64), torch.zeros(0))
        self.mild.add(kid, desc)
        best: _LoopEdge | None = None
        near = self._near_keyframes(kid)
        found = ids.tolist()
        for cand in found + [j for j in near if j not in found]:
            if cand > kid - cfg.loop.min_separation:
                continue
            self.loops["candidates"] += 1
            if cand in near:
                self.loops["proximity_candidates"] += 1
            edge = self._verify(cand, kf, centred=cand in near)
            if edge is not None and (best is None or edge.psr > best.psr):
                best = edge
        if best is None:
            return
        self.loops["verified"] += 1
        best = self._refine_loop(best, kf)
        self._try_loop(best.candidate, kid, best.T_jk, best.variance, rotation_cov=best.rotation_cov)

    @property
    def _refines_loops(self) -> bool:
        """Whether verified loops are refined over the old keyframe's map: ``loop.visual_rotation``
        with an inertial attitude (ground truth's rotation is never replaced)."""
        return self.cfg.loop.visual_rotation and self.attitude.source != "groundtruth"

    def _refine_loop(self, edge: _LoopEdge, kf: _Keyframe) -> _LoopEdge:
        """``edge`` with its pose refined over the candidate's map and its rotation's covariance.

        Only with ``loop.visual_rotation`` and an inertial attitude; unchanged where the
        refinement does not converge. The refinement's covariance is of a left perturbation in
        the old keyframe's axes; the graph's residual is in the new keyframe's, so it is rotated
        by ``R_jk``, and ``visual_rotation_sigma_deg`` is added per axis.
        """
        if not self._refines_loops or kf.cloud is None:
            return edge
        old = self.keyframes[edge.candidate]
        c = kf.cloud
        res = refine_against_map(c.points, c.grey, c.valid, old.map, old.resolution, edge.T_jk[None].to(c.points.device))
        if not bool(res.converged[0]):
            self.visual_rotation["not_converged"] += 1
            return edge
        T = res.T[0].cpu()
        R = T[:3, :3]
        floor = math.radians(self.cfg.loop.visual_rotation_sigma_deg) ** 2
        cov = R.T @ res.covariance[0, 3:, 3:].cpu() @ R + torch.eye(3, dtype=torch.float64) * floor
        change = math.degrees(float(so3_log(edge.T_jk[:3, :3].T @ R).norm()))
        self.visual_rotation["refined"] += 1
        self.visual_rotation["max_change_deg"] = max(self.visual_rotation["max_change_deg"], change)
        return replace(edge, T_jk=T, rotation_cov=cov)

    def _local_window(self, kid: int) -> None:
        """Register keyframe ``kid`` against the ``loop.local_window`` keyframes before its predecessor.

        Each match that verifies like a loop candidate (``_verify``) and passes the same
        chi-square test on the window's graph (its oldest keyframe held) adds an edge; the
        window is optimised with it.
        """
        lo = max(0, kid - 1 - self.cfg.loop.local_window)
        kf = self.keyframes[kid]
        for cand in range(kid - 2, lo - 1, -1):
            edge = self._verify(cand, kf)
            if edge is None:
                continue
            self.local["verified"] += 1
            self._try_loop(cand, kid, edge.T_jk, edge.variance, window=lo)

    def _near_keyframes(self, kid: int) -> list[int]:
        """The ``loop.proximity_candidates`` keyframes nearest to keyframe ``kid`` in the pose graph.

        Only keyframes at least ``loop.min_separation`` older, within ``loop.max_rotation_deg``
        of its attitude and whose orthographic image would overlap most of it: the graph's
        in-plane offset at most ``loop.proximity_radius`` times the old keyframe's image
        half-height (``r_k H / 2``). Nearest first (3-D distance in the graph).
        """
        lc = self.cfg.loop
        first_late = kid - lc.min_separation + 1
        if lc.proximity_candidates == 0 or first_late <= 0:
            return []
        kf = self.keyframes[kid]
        old = self.keyframes[:first_late]
        T = torch.stack([o.T_wk for o in old])  # (J, 4, 4) float64, host
        r = torch.cat([o.resolution for o in old]).to("cpu", torch.float64)  # one read-back
        R_j, p_j = T[:, :3, :3], T[:, :3, 3]
        # angle between attitudes from the trace of R_j^T R_k; offset in each old keyframe's axes
        cos = ((R_j * kf.T_wk[:3, :3]).sum(dim=(1, 2)) - 1.0) / 2.0
        angle = torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))
        d = torch.einsum("jab,ja->jb", R_j, kf.T_wk[:3, 3] - p_j)
        near = (angle <= lc.max_rotation_deg) & (d[:, :2].norm(dim=1) <= lc.proximity_radius * r * self.cfg.kcc.ortho_height / 2)
        idx = near.nonzero()[:, 0]
        order = d[idx].norm(dim=1).argsort(stable=True)
        return idx[order][: lc.proximity_candidates].tolist()

    def _verify(self, cand: int, kf: _Keyframe, centred: bool = False) -> _LoopEdge | None:
        """Correlate keyframe ``kf``'s cloud against candidate ``cand``'s fused map.

        ``centred``: ``kf``'s orthographic image is centred on the graph's estimate of its offset
        from the candidate (``track_step``'s ``center``), as frames are on their prediction;
        else on its own axis (an appearance candidate, whose graph offset may be far off).
        """
        lc = self.cfg.loop
        old = self.keyframes[cand]
        R_jk = old.T_wk[:3, :3].T @ kf.T_wk[:3, :3]
        if math.degrees(float(so3_log(R_jk).norm())) > lc.max_rotation_deg:
            return None
        filt = self._ensure_filter(old)
        c = kf.cloud
        center = _content_center(old.T_wk, kf.T_wk[:3, 3], c.points) if centred else None
        res = track_step(c.points, c.grey, c.valid, R_jk[None], old.map, filt, old.resolution, self.correlator, center)
        old.filter = None  # keep memory flat: old keyframes' filters are rebuilt on demand
        m = summarize(res)[0]
        if m.psr < lc.min_psr or not m.depth_ok or m.matched_fraction < lc.min_matched:
            return None
        return _LoopEdge(cand, se3_from_Rt(R_jk, -m.t_content), m.variance, m.psr)

    def _edges(self):
        return (
            torch.tensor(self.edges_i, dtype=torch.int64),
            torch.tensor(self.edges_j, dtype=torch.int64),
            torch.stack(self.edges_T),
            torch.stack(self.edges_info),
            torch.stack(self.edges_test_info),
        )

    def _try_loop(
        self, j_old: int, k_new: int, T_jk: Tensor, variance: Tensor, window: int | None = None, rotation_cov: Tensor | None = None,
    ) -> bool:
        """Test the edge ``j_old -> k_new`` against the graph; keep it and its optimisation if consistent.

        Args:
            j_old, k_new: the keyframes the edge joins.
            T_jk: (4, 4) the edge's measured transform.
            variance: (3,) its translation variance, m^2.
            window: None for a loop (the whole graph, keyframe 0 held); else the oldest keyframe
                of a local window (``_local_window``): only the keyframes from it on and the
                edges among them take part, that keyframe held.
            rotation_cov: (3, 3) covariance of the edge's rotation where it was measured
                (``_refine_loop``); None: the attitude's rotation, which carries no information.

        Returns:
            Whether the edge was accepted.
        """
        t0 = self._tic()
        lc = self.cfg.loop
        span = self.keyframes[k_new].timestamp - self.keyframes[j_old].timestamp
        info = self._information(T_jk, variance, span, 0.0, loop=True, rotation_cov=rotation_cov)
        test_info = info
        if self._jitter_test:
            depth = self.keyframes[k_new].depth
            test_info = self._information(
                T_jk, variance, span, depth, loop=True, extra=self._drift_variance(j_old, k_new), rotation_cov=rotation_cov,
            )
        i, j, T_ij, info_all, test_all = self._edges()
        T0 = torch.stack([kf.T_wk for kf in self.keyframes])
        lo = 0 if window is None else window
        if lo:
            inside = (i >= lo) & (j >= lo)
            i, j, T_ij, info_all, test_all, T0 = i[inside] - lo, j[inside] - lo, T_ij[inside], info_all[inside], test_all[inside], T0[lo:]
        test = edge_consistency(
            T0, i, j, T_ij, test_all, j_old - lo, k_new - lo, T_jk.to(torch.float64), test_info, lc.chi2_quantile,
            fixed=0, config=LMConfig(iterations=20, tol=1e-10),
        )
        res = test.result
        if self._jitter_test and test.consistent:
            # The test's covariances decide; the graph is optimised with the paper's (Eq. (19)),
            # under which the loop, trusted more than the odometry, corrects the whole drift.
            res = optimize_pose_graph(
                res.T_wc, torch.cat([i, torch.tensor([j_old - lo])]), torch.cat([j, torch.tensor([k_new - lo])]),
                torch.cat([T_ij, T_jk.to(torch.float64)[None]]), torch.cat([info_all, info[None]]),
                fixed=0, config=LMConfig(iterations=20, tol=1e-10),
            )
        odo = ~torch.tensor(self.edges_loop, dtype=torch.bool)
        if lo:
            odo = odo[inside]
        bend = float(edge_residuals(res.T_wc, i[odo], j[odo], T_ij[odo])[:, :3].norm(dim=-1).max()) if bool(odo.any()) else 0.0
        self.posegraph_ms.append(1000 * (time.perf_counter() - t0))
        self.monitor.scalar("optimization/posegraph_ms", self.posegraph_ms[-1], self.keyframes[k_new].frame_index)
        self._toc("posegraph", t0)
        chi2 = float(test.chi2_increase)
        if math.isfinite(chi2):
            # The test's statistic against its threshold, per loop trial (TensorBoard).
            tag = "optimization/loop_chi2" if window is None else "optimization/window_chi2"
            self.monitor.scalar(tag, chi2 / test.threshold, self.keyframes[k_new].frame_index)
        if window is None:
            self.loop_tests.append(
                {"keyframe": k_new, "candidate": j_old, "chi2_increase": chi2 if math.isfinite(chi2) else None, "threshold": test.threshold}
            )
        counts = self.loops if window is None else self.local
        if not test.consistent and math.isfinite(chi2):
            counts["rejected_by_chi2"] += 1
            logger.info("edge %d -> %d rejected: chi2 increase %.2f > %.2f", j_old, k_new, chi2, test.threshold)
            return False
        if not test.consistent or bend > lc.max_odometry_bend_m:
            counts["rejected_by_odometry"] += 1
            logger.info("edge %d -> %d rejected: odometry bent by %.3f m", j_old, k_new, bend)
            return False
        self._add_edge(j_old, k_new, T_jk, info, test_info, loop=True)
        counts["accepted"] += 1
        # The camera's velocity does not change with the correction; its direction turns with the
        # newest keyframe's rotation.
        v = self._velocity()
        R_before = self.keyframes[-1].T_wk[:3, :3]
        self._history_start = len(self.frames)
        for kf, T in zip(self.keyframes[lo:], res.T_wc):
            kf.T_wk = T
        if self.accel is not None:
            # The frames of the compensation's window moved with their keyframes: it goes on with
            # their new positions.
            self.accel.reposition(self._world_positions(self.accel.held))
        self._carried_velocity = None if v is None else (self.keyframes[-1].T_wk[:3, :3] @ R_before.T) @ v
        # Fuse the back-end into the attitude: the newest keyframe's optimised rotation replaces
        # the stream's, and the same correction applies to the frames that follow.
        newest = self.keyframes[-1]
        self.R_corr = newest.T_wk[:3, :3] @ newest.R_att.T
        self.monitor.scalar("progress/loops_accepted", self.loops["accepted"], self.keyframes[-1].frame_index)
        return True

    # ------------------------------------------------------------------ output
    def _output_keyframe_poses(self) -> Tensor:
        """(K, 4, 4) keyframe poses in the output world: the first keyframe's camera frame.

        Internally the world is the attitude stream's (gravity-aligned, at the first camera's
        position); trajectory.txt, keyframes.txt and map.ply share GC-SLAM's convention instead:
        the world is the camera frame of the first keyframe (x right, y down, z forward). The
        pose graph holds keyframe 0 fixed, so that frame does not move.
        """
        T_wk = torch.stack([kf.T_wk for kf in self.keyframes])
        return se3_inverse(T_wk[0]) @ T_wk

    def estimate_so_far(self) -> Trajectory | None:
        """Every frame tracked so far in the current keyframe poses, at the depth instants (output world)."""
        if not len(self.frames):
            return None
        return self.frames.so_far(self._output_keyframe_poses())

    def progress_counters(self) -> dict[str, float]:
        """Keyframes, loops, fused frames and the last PSR, for TensorBoard."""
        out = {
            "keyframes": float(len(self.keyframes)),
            "loops_accepted": float(self.loops["accepted"]),
            "loops_rejected": float(self.loops["rejected_by_odometry"] + self.loops["rejected_by_chi2"]),
            "fused_frames": float(self.fused),
            "prior_frames": float(self.motion_prior_frames),
        }
        if self.psr and math.isfinite(self.psr[-1]):
            out["psr"] = float(self.psr[-1])
        return out

    def finish(self) -> SystemOutput:
        """The trajectory at the frame timestamps, the keyframes and the map (output world).

        Each tracked pose is the camera's at the depth image's instant (``Frame.geometry_time``); the
        trajectory is reported at the frame timestamps, so it is interpolated there (linear in
        translation, SLERP in rotation) between the neighbouring depth instants. On TUM fr1 the
        two alternate ~15 ms before and after the colour stamp, which at 0.4 m/s is ±6 mm.
        Poses outside the span of depth instants, or across a gap longer than
        ``attitude_max_gap``, are kept as tracked. Keyframes are reported at their depth
        instants, as tracked.
        """
        self._ahead.clear()  # frames prepared and never tracked (a stop before the end)
        log = self.frames
        if not len(log):
            return FrameLog.empty(dict(self.stage_ms), self._metrics())
        T_wk = self._output_keyframe_poses()
        T_wc = log.at_frame_times(log.poses(T_wk), self.cfg.attitude_max_gap)
        points, colors = self._map_points(T_wk)
        return log.output(
            T_wc, [kf.frame_index for kf in self.keyframes], T_wk, points, colors, dict(self.stage_ms), self._metrics(),
            log.prior_indices(),
        )

    def _metrics(self) -> dict[str, Any]:
        psr = torch.tensor([p for p in self.psr if math.isfinite(p)], dtype=torch.float64)
        stats = (
            {"mean": float(psr.mean()), "median": float(psr.median()), "min": float(psr.min()), "max": float(psr.max())}
            if len(psr) else {}
        )
        return {
            "attitude_source": self.attitude.source,
            "attitude_time_offset_s": self.cfg.attitude_time_offset,
            # null: off, or an attitude no filter made (ground truth)
            "accel_compensation": None if self.accel is None else {
                "imu_samples": self.accel.compensated_samples, "max_correction_deg": self.accel.max_correction_deg,
            },
            "psr": stats,
            "fused_frames": self.fused,
            "motion_prior_frames": self.motion_prior_frames,
            "untracked": dict(self.untracked),
            "loops": dict(self.loops),
            "loop_tests": list(self.loop_tests),
            "local_window": dict(self.local),
            # null: off (or loops off), or ground-truth attitude (never refined)
            "loop_visual_rotation": dict(self.visual_rotation) if self.cfg.loop.enabled and self._refines_loops else None,
            "odometry_variances": dict(self.odometry_variances),
            "posegraph_ms_max": max(self.posegraph_ms) if self.posegraph_ms else None,
        }

    def _map_points(self, T_wk: Tensor) -> tuple[Tensor, Tensor]:
        """Back-project every keyframe's fused orthographic map into the world, voxel-downsampled, in colour."""
        k = self.cfg.kcc
        H, W = k.ortho_height, k.ortho_width
        rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
        pts, cols_out = [], []
        for kf, T in zip(self.keyframes, T_wk):
            m = kf.map.valid[0].cpu()
            r = float(kf.resolution[0])
            # Orthographic pixel centres in the keyframe's own camera frame (rotation = identity).
            xyz = torch.stack([(cols[m] + 0.5 - W / 2) * r, (rows[m] + 0.5 - H / 2) * r, kf.map.depth[0].cpu()[m].double()], -1)
            pts.append(xyz @ T[:3, :3].T + T[:3, 3])
            # The keyframe's colour where it saw the pixel; pixels only later frames filled in
            # (fusion) carry their fused grey.
            grey = kf.map.grey[0].cpu()[m].double()[:, None].expand(-1, 3)
            if kf.colour is not None:
                colour, has = _fill_colour(kf.colour.double() / 255, kf.colour_valid, m)
                grey = torch.where(has[m][:, None], colour.permute(1, 2, 0)[m], grey)  # (P, 3)
            cols_out.append(grey)
        return voxel_downsample(torch.cat(pts), torch.cat(cols_out), self.cfg.map_voxel)


def _fill_colour(colour: Tensor, has: Tensor, want: Tensor, rounds: int = 16) -> tuple[Tensor, Tensor]:
    """Spread a keyframe's orthographic colours into the map pixels only its holes-filled map holds.

    The orthographic map is finer than a small image's points (and fusion fills more pixels), so
    each round gives every wanted pixel without a colour the mean of its coloured 3x3 neighbours.
    It runs on the host (the keyframe colours are kept there), each round's 3x3 sums as one
    OpenCV box filter over the colours and their count (zero outside the image).

    Args:
        colour: (3, H, W) float64 colours in [0, 1], valid where ``has``.
        has: (H, W) bool pixels holding a colour.
        want: (H, W) bool pixels of the map.
        rounds: most rounds (pixels farther than this from any colour keep none).

    Returns:
        (colour (3, H, W), has (H, W)) after filling, on the CPU.
    """
    c = np.ascontiguousarray(colour.detach().cpu().to(torch.float64).permute(1, 2, 0).numpy())  # (H, W, 3), a copy
    got = has.cpu().numpy().copy()
    wanted = want.cpu().numpy()
    # The coloured pixels' colours and a 1 (zero elsewhere), kept up to date pixel by pixel as
    # pixels are filled (rewriting the whole strided image each round cost most of its time).
    stack = np.empty(c.shape[:2] + (4,), dtype=np.float64)
    np.multiply(c, got[..., None], out=stack[..., :3])
    stack[..., 3] = got
    for _ in range(rounds):
        todo = wanted & ~got
        if not todo.any():
            break
        # 3x3 sums of the coloured pixels' colours and of their count (zero outside).
        sums = cv2.boxFilter(stack, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        new = np.flatnonzero(todo & (sums[..., 3] > 0))  # as flat indices: one mask scan, then gathers
        if not len(new):
            break  # nothing reachable is left: further rounds would not change anything
        at = sums.reshape(-1, 4)[new]
        filled = at[:, :3] / at[:, 3:]
        c.reshape(-1, 3)[new] = filled
        at[:, :3] = filled
        at[:, 3] = 1.0
        stack.reshape(-1, 4)[new] = at
        got.reshape(-1)[new] = True
    return torch.from_numpy(c).permute(2, 0, 1), torch.from_numpy(got)


def _memory(cfg: NISlamConfig, camera, batch: int) -> dict[str, tuple[int, str]]:
    """NI-SLAM's orthographic images and their spectra, per sequence (``systems.memory``)."""
    k = cfg.kcc
    return {"orthographic images": (NISLAM_BYTES_PER_ORTHO_PIXEL * k.ortho_height * k.ortho_width * batch,
                                    f"kcc.ortho_height x kcc.ortho_width = {k.ortho_height} x {k.ortho_width}")}


# Orthographic pixels per batched call on the CPU: ``max_batch`` defaults to this over the
# orthographic image size (at least 1). On the CPU a batched call saves per-operation overhead
# but its images leave the caches as B grows (``scripts/bench_batch.py`` measures the trade-off);
# on other devices the whole group is one batch.
CPU_BATCH_PIXELS = 2**18


def _max_batch(cfg: NISlamConfig, device: str, n: int) -> int:
    """Sequences per batched call: ``CPU_BATCH_PIXELS`` worth of orthographic images on the CPU, else all ``n``."""
    if str(device).startswith("cpu"):
        return max(1, CPU_BATCH_PIXELS // (cfg.kcc.ortho_height * cfg.kcc.ortho_width))
    return max(n, 1)


SPEC = SystemSpec(
    name="nislam",
    description="NI-SLAM: non-iterative RGB-D-inertial odometry with kernel cross-correlators",
    config_cls=NISlamConfig,
    build=NISlam,
    memory=_memory,
    # Every sequence keeps its keyframe images at once.
    lockstep=LockstepSpec(step=track_frames, max_batch=_max_batch, holds_all=True),
)
