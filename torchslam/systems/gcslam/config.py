"""GC-SLAM's settings: the front-end choice, registration, keyframes, loops and FastGO."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import ClassVar

from ...errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, check_limits, parse_choice
from ...features import ORBConfig
from ...loop import MILDConfig
from ...registration.dense import DenseConfig
from ...registration.rolling import check_readout
from ...registration.sparse import SparseConfig

# ``readout_time``'s value that takes the sequence's own readout.
AUTO = "auto"

__all__ = ["Frontend", "GCSlamConfig"]


class Frontend(str, enum.Enum):
    """How a frame is registered to its keyframe.

    SPARSE: ORB features, isometry filter, RANSAC and refinement (:mod:`torchslam.registration.sparse`).
    DENSE: photometric + geometric alignment on an image pyramid (:mod:`torchslam.registration.dense`).
    """

    SPARSE = "sparse"
    DENSE = "dense"


@dataclass(frozen=True)
class GCSlamConfig:
    """Settings of GC-SLAM. Defaults follow the authors' released code where the paper is silent.

    Attributes:
        frontend: :class:`Frontend`, ``sparse`` (ORB registration) or ``dense`` (photometric +
            geometric); the strings are accepted too.
        orb_features: ORB features per frame (released code: 2000).
        orb_scale: ORB pyramid scale factor (1.2).
        orb_levels: ORB pyramid levels (8).
        orb_min_fast_threshold: FAST threshold of a starved frame (strong motion blur, dim
            light): one with fewer than a tenth of ``orb_features`` keypoints at OpenCV's threshold
            of 20 is detected again at this one (ORB-SLAM's 7; torchslam's, beyond the paper; 20
            or more: off). ``features.ORBConfig.min_fast_threshold``; docs/results/gcslam.md, "Blurred frames
            detected again".
        sparse: sparse registration settings (isometry filter, RANSAC, refinement).
        dense: dense registration settings (320x240 pyramid).
        keyframe_displacement: a frame becomes a keyframe when the keyframe's points move by
            more than this fraction of the focal length on average (released code: 0.1).
        keyframe_sample_stride: pixel stride of the keyframe points used for that test.
        keyframe_weak_ratio: a tracked frame that keeps fewer correspondences than this fraction
            of the most a frame kept to the current keyframe makes the previous tracked frame (if
            it kept more) a keyframe, and is registered to that one instead (torchslam's, for
            blurred stretches; 0: off). Such a promoted keyframe joins MILD but proposes no loops.
        dense_orb_start: with the dense front-end, a registration that fails or keeps fewer than
            ``keyframe_weak_ratio`` of the best correspondence count to the current keyframe (of
            the count of the registration that linked the keyframe, before any frame is tracked
            to it) is started again from an ORB registration of the frame to the keyframe, and the one
            with more correspondences is kept (torchslam's; the sparse front-end's guided
            matches fall back to brute force alike). A start from the motion prior that is far
            off, as at a sudden reversal of fast motion, otherwise converges to a wrong pose.
        dense_orb_start_residual: with ``dense_orb_start``, a dense registration that kept its
            correspondences is also started again from ORB when its photometric RMS residual
            exceeds this multiple of the median of the last 10 tracked registrations', or while
            fewer than 3 are known (a run's first registrations), and the one with the lower
            residual is kept (torchslam's; 0: off). A wrong basin
            keeps its correspondences (the depth still overlaps) but not its photometric fit:
            docs/results/gcslam.md, "Dense registrations started again from ORB at an outlying residual".
        dense_orb_keyframe_check: with ``dense_orb_start``, a dense registration that makes its
            frame a keyframe (the graph's odometry link) is checked against the frame's ORB
            registration to the keyframe (brute-force matching, independent of the start): where
            the two poses place the ORB inliers more than ``sparse.inlier_threshold`` apart on
            average, the dense registration is started again from the ORB pose and the one with
            the lower photometric residual is kept (torchslam's). docs/results/gcslam.md, "Keyframe links
            checked against ORB".
        mild: loop detector settings (16 tables of 16-bit substrings, top 5 candidates).
        loops: look for loop closures at every new keyframe.
        fastgo_iterations: FastGO Gauss-Newton iterations per keyframe (released code: 3).
        fastgo_every_keyframe: run those iterations after every keyframe, as the paper does.
            False (torchslam's default): only for a keyframe with loop candidates, just before
            they are tested. A keyframe without candidates adds one node linked by one pair (a
            leaf), placed by that pair's registration, which leaves the optimum of the rest of
            the graph where it was; the loop test's trial optimisation, and the final run,
            optimise everything (docs/results/gcslam.md, "FastGO only before a loop test").
        loop_iterations: iterations of the trial optimisation that tests loop candidates.
        loop_threshold: reject loops that raise the RMS registration error of the earlier pairs
            by more than this fraction (released code: 5 %) plus ``loop_slack_m``.
        loop_slack_m: absolute slack of that test, metres. Real registrations are biased by
            millimetres (colour/depth timing, rolling shutter), so a true loop over a chain of
            such pairs raises their RMS error by millimetres, which the relative rule alone
            would reject; a false loop moves the error by centimetres.
        final_iterations: iterations of one last FastGO run over all keyframes at the end of
            the sequence (0: keep the poses as the last loop test or per-keyframe run left them,
            with the keyframes since placed by their odometry pairs).
        threaded: run optimisation in the background (False: inline, for tests).
        background: where the background optimisation runs: ``"process"``, a child process
            (on the CPU where the fork start method exists: Linux; elsewhere the thread), or
            ``"thread"``. The optimiser's and the tracker's many small tensor operations contend
            for Python's interpreter lock in two threads, so only a process overlaps them; the
            results are the same.
        prepare_ahead: in ``run_sequence``, each frame's ORB features (sparse) or dense pyramid
            (dense) are computed on a thread of their own while the frames before it are tracked
            (``systems.base.AheadFrames``): the same results, overlapped with tracking where a
            core is free. False: prepared inline by ``track``.
        prepare_ahead_in: where that preparation and the reading of the frames run:
            ``"process"``, a child process forked after ``start`` (on the CPU where the fork start
            method exists; elsewhere the thread), which shares no interpreter lock with tracking
            (``systems.ahead_process``), or ``"thread"``. The same results either way.
        relocalize_keyframes: recent keyframes tried when a frame cannot be registered.
        max_lost: lost frames in a row before a new, unlinked keyframe is started.
        min_valid_depth: frames with fewer valid depth pixels are not tracked.
        spread_corrections: in the trajectory, the frames tracked against a keyframe follow the
            correction the optimisation made to the link from that keyframe to the next one, in
            proportion to their time along it (``FrameLog.poses``' ``spread``; beyond the paper,
            whose frames move with their keyframe alone). Keyframe poses are unchanged. docs/results/gcslam.md,
            "Frames between keyframes follow both".
        interpolation_max_gap: largest gap between depth instants across which the trajectory is
            interpolated to the colour timestamps, seconds.
        map_stride: pixel stride of the keyframe clouds in ``map.ply``.
        map_voxel: voxel size of ``map.ply``, metres.
        max_depth: depth beyond this is ignored for the map, metres.
        motion_prior: the predicted pose of a frame's registration (the dense front-end starts
            from it, the sparse one guides its matches by it, ``sparse.guided_radius``):
            ``"constant_velocity"`` continues the last
            tracked step's motion over the time since (beyond the paper: fewer Gauss-Newton
            iterations and a better start under fast motion), ``"none"`` starts from the last
            frame's pose. After a lost frame, a relocalisation or a long gap
            (``motion_prior_max_gap``) the last frame's pose is used.
        motion_prior_max_gap: longest time over which the velocity is continued, seconds.
        keyframe_pairs: how the pairs of the pose graph (a new keyframe and its reference, a
            loop) are measured. ``"sparse"``: by their ORB registration, as the paper.
            ``"dense"`` (beyond the paper): every pair that ORB features registered (the sparse
            front-end's keyframes, relocalised keyframes, loops) is registered again densely,
            photometrically and geometrically from that pose, and enters FastGO with the dense
            correspondences' statistics; where the dense registration fails the ORB one stays.
            ``"auto"``: ``dense`` with either front-end (the dense one's tracked pairs are dense
            already, so there it measures its loops and relocalised keyframes densely, the loops
            at their ORB weight, ``loop_pair_weight``: docs/results/gcslam.md, "Densely measured loops weighted
            as their ORB registration").
        loop_pair_weight: the weight in FastGO of a loop measured densely (``keyframe_pairs``).
            ``"correspondences"``: its dense correspondences' own (FastGO weighs a pair by its
            weighted correspondence count, tens of thousands for a dense pair); ``"orb"``
            (beyond the paper): its statistics scaled to the total weight of the loop's ORB
            registration, i.e. the dense pose with the ORB pair's pull (docs/results/gcslam.md, "Densely measured
            loops weighted as their ORB registration"); ``"auto"``: ``orb`` with the dense
            front-end, ``correspondences`` with the sparse one.
        depth_refine_points: sparse front-end (beyond the paper): each frame's ORB registration to
            its keyframe is refined against the keyframe's depth image with the frame's depth
            at a lattice of about this many pixels (DVO's geometric residual) together with the
            ORB inliers (:func:`~torchslam.registration.depth_align.refine_with_depth`). 0: the
            ORB pose as registered. Frame-to-frame error (RPE over one frame) was lower on every
            real and synthetic sequence measured (TUM fr1/xyz 4.85 -> 3.63 mm); docs/results/gcslam.md, "Sparse
            poses refined against the keyframe's depth". Chosen before measuring, not tuned.
        depth_refine_iterations: Gauss-Newton steps of that refinement.
        readout_time: the sensor's rolling shutter, seconds from its first image row to its last
            (0: a global shutter, as the paper assumes; a Kinect v1 reads its rows over about
            30 ms), or ``auto`` (default): the sequence's own (``Sequence.readout_time``: a
            folder's ``calibration.txt`` ``readout`` line, else its name's sensor, 0.03 s for the
            Kinect v1 datasets TUM freiburg1/2 and 7-Scenes, else 0;
            :func:`~torchslam.data.calibration.readout_for`). A frame's stamp is taken as its
            middle row's instant. What a front-end registers of each frame is moved to the stamp
            with the tracker's constant-velocity motion before it is registered: the dense
            pyramid's points, or the sparse front-end's ORB points and depth samples. A keyframe
            is moved so for tracking, its pairs and its loops: the dense front-end resamples its
            images; the sparse one moves its ORB points, resamples the working images of its
            dense pairs, and its depth refinement compares each point with the keyframe depth
            its row read (:mod:`torchslam.registration.rolling`; docs/results/gcslam.md,
            "Rolling shutter"). A keyframe made with no motion yet (the first, one after a loss)
            is moved with the motion of the first frame tracked against it, before the optimiser
            gets it.
    """

    frontend: Frontend = Frontend.SPARSE
    orb_features: int = 2000
    orb_scale: float = 1.2
    orb_levels: int = 8
    orb_min_fast_threshold: int = 7
    sparse: SparseConfig = field(default_factory=SparseConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    keyframe_displacement: float = 0.1
    keyframe_sample_stride: int = 16
    keyframe_weak_ratio: float = 0.5
    dense_orb_start: bool = True
    dense_orb_start_residual: float = 3.0
    dense_orb_keyframe_check: bool = True
    mild: MILDConfig = field(default_factory=MILDConfig)
    loops: bool = True
    fastgo_iterations: int = 3
    fastgo_every_keyframe: bool = False
    loop_iterations: int = 10
    loop_threshold: float = 0.05
    loop_slack_m: float = 0.003
    final_iterations: int = 10
    threaded: bool = True
    background: str = "process"
    prepare_ahead: bool = True
    prepare_ahead_in: str = "process"
    relocalize_keyframes: int = 5
    max_lost: int = 10
    min_valid_depth: int = 1000
    spread_corrections: bool = True
    interpolation_max_gap: float = 0.1
    map_stride: int = 4
    map_voxel: float = 0.01
    max_depth: float = 5.0
    motion_prior: str = "constant_velocity"
    motion_prior_max_gap: float = 0.2
    keyframe_pairs: str = "auto"
    loop_pair_weight: str = "auto"
    depth_refine_points: int = 3000
    depth_refine_iterations: int = 3
    readout_time: float | str = "auto"

    LIMITS: ClassVar[dict[str, Limit]] = {
        "orb_features": AT_LEAST_1, "orb_scale": Limit(gt=1), "orb_levels": AT_LEAST_1, "orb_min_fast_threshold": Limit(ge=0, le=255),
        "keyframe_displacement": POSITIVE,
        "keyframe_weak_ratio": Limit(ge=0, lt=1), "dense_orb_start_residual": NON_NEGATIVE,
        "keyframe_sample_stride": AT_LEAST_1, "fastgo_iterations": AT_LEAST_1, "loop_iterations": AT_LEAST_1,
        "loop_threshold": NON_NEGATIVE, "loop_slack_m": NON_NEGATIVE, "final_iterations": NON_NEGATIVE,
        "relocalize_keyframes": NON_NEGATIVE, "max_lost": NON_NEGATIVE, "min_valid_depth": AT_LEAST_1,
        "interpolation_max_gap": POSITIVE, "map_stride": AT_LEAST_1, "map_voxel": POSITIVE, "max_depth": POSITIVE,
        "motion_prior_max_gap": POSITIVE, "depth_refine_points": NON_NEGATIVE, "depth_refine_iterations": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "frontend", parse_choice(Frontend, self.frontend, "frontend"))
        if self.background not in ("process", "thread"):
            raise ConfigError(f"background: expected 'process' or 'thread', got {self.background!r}")
        if self.prepare_ahead_in not in ("process", "thread"):
            raise ConfigError(f"prepare_ahead_in: expected 'process' or 'thread', got {self.prepare_ahead_in!r}")
        if self.motion_prior not in ("constant_velocity", "none"):
            raise ConfigError(f"motion_prior: expected 'constant_velocity' or 'none', got {self.motion_prior!r}")
        if self.keyframe_pairs not in ("auto", "sparse", "dense"):
            raise ConfigError(f"keyframe_pairs: expected 'auto', 'sparse' or 'dense', got {self.keyframe_pairs!r}")
        if self.loop_pair_weight not in ("auto", "correspondences", "orb"):
            raise ConfigError(f"loop_pair_weight: expected 'auto', 'correspondences' or 'orb', got {self.loop_pair_weight!r}")
        check_limits(self)
        if self.readout_time != AUTO:
            try:
                object.__setattr__(self, "readout_time", check_readout(self.readout_time, "readout_time"))
            except ConfigError as exc:
                raise ConfigError(f"{exc}; or '{AUTO}': the sequence's own") from None

    def readout_for(self, sequence) -> tuple[float, str | None]:
        """``(seconds, source)`` of the rolling-shutter readout a run of ``sequence`` models
        (``readout_time``, ``auto`` resolved): the sequence's own (``Sequence.readout_time``; 0
        and None where it has none); a number as set, source ``"readout_time"``."""
        if self.readout_time != AUTO:
            return float(self.readout_time), "readout_time"
        seconds = check_readout(getattr(sequence, "readout_time", 0.0), f"{getattr(sequence, 'name', 'sequence')}: readout_time")
        return seconds, getattr(sequence, "readout_source", None) if seconds > 0 else None

    @property
    def dense_pairs(self) -> bool:
        """Whether ORB-registered pose-graph pairs are registered again densely (``keyframe_pairs``, ``auto`` resolved)."""
        return self.keyframe_pairs in ("auto", "dense")

    @property
    def loops_at_orb_weight(self) -> bool:
        """Whether a densely measured loop enters FastGO with its ORB registration's total weight (``loop_pair_weight``, ``auto`` resolved)."""
        if self.loop_pair_weight == "auto":
            return self.frontend is Frontend.DENSE
        return self.loop_pair_weight == "orb"

    def orb(self) -> ORBConfig:
        """The ORB extractor's settings."""
        return ORBConfig(n_features=self.orb_features, scale_factor=self.orb_scale, n_levels=self.orb_levels,
                         min_fast_threshold=self.orb_min_fast_threshold)
