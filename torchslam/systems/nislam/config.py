"""NI-SLAM settings: the system's config, its loop-closure section and its options as Enums."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import ClassVar

from ...errors import AT_LEAST_1, FRACTION, NON_NEGATIVE, POSITIVE, ConfigError, Limit, check_limits, parse_choice
from ...imu import ImuNoise
from ...kcc import KCCConfig

__all__ = ["AttitudeSource", "Gravity", "LoopConfig", "NISlamConfig", "AcceptanceCovariance"]


class AttitudeSource(str, enum.Enum):
    """Where NI-SLAM's rotations come from (``NISlamConfig.attitude``)."""

    AUTO = "auto"
    IMU = "imu"
    SIMULATED = "simulated"
    GROUNDTRUTH = "groundtruth"


class Gravity(str, enum.Enum):
    """World direction of gravity for the simulated attitude (``NISlamConfig.gravity``)."""

    AUTO = "auto"
    X = "x"
    NEG_X = "-x"
    Y = "y"
    NEG_Y = "-y"
    Z = "z"
    NEG_Z = "-z"


class AcceptanceCovariance(str, enum.Enum):
    """The edge covariances NI-SLAM's loop test uses (``LoopConfig.acceptance_covariance``)."""

    JITTER = "jitter"
    EQ19 = "eq19"


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure on keyframes (NI-SLAM §9).

    Attributes:
        enabled: look for loops at every new keyframe.
        orb_features: ORB features kept per keyframe (the paper: 1000).
        min_separation: candidates must be at least this many keyframes older (3: a camera
            sweeping back and forth over one place, as on TUM fr1/xyz, meets its own keyframes
            of the last sweep two or three keyframes back; docs/results/nislam.md, "Loops on revisits").
        top_k: candidates verified per new keyframe.
        min_score: smallest place-recognition score of a candidate.
        min_psr: smallest KCC PSR for a verified loop.
        min_matched: smallest fraction of well-matched orthographic pixels for a verified loop.
        max_rotation_deg: largest attitude difference between the two keyframes (the
            orthographic views of two very different attitudes share little).
        chi2_quantile: a verified loop is accepted when the chi-square increase of the optimised
            pose graph it causes (``backend.edge_consistency``: for a linear-Gaussian graph the
            Mahalanobis norm of the loop's innovation against the graph's predicted relative-pose
            covariance) is at most this quantile of the chi-square distribution with the loop
            edge's degrees of freedom (3 where the verification measures translation and its
            rotation is the attitude's own, already in the graph; 6 where ``visual_rotation``
            measured the rotation too). 0.999 rejects one true loop in a thousand
            when the edges' covariances are honest.
        max_odometry_bend_m: an extra guard after the statistical test: reject the loop when,
            after optimisation, any odometry edge's translation residual exceeds this, metres
            (the paper's comparison with the front-end odometry, §9.2); ``inf`` (the default)
            turns it off: a long drift legitimately bends some edges by more than any fixed
            distance.
        rotation_sigma_deg: standard deviation of an odometry edge's rotation with an inertial
            attitude (``imu`` or ``simulated``) at zero time between its keyframes, degrees (the
            AHRS's per-sample error); the drift below adds to it.
        groundtruth_rotation_sigma_deg: the same with ground-truth attitude (exact up to the
            ground truth's own noise), degrees.
        gyro_bias_sigma: gyro bias an inertial attitude leaves uncorrected, rad/s: the rotation
            variance of an odometry edge whose keyframes are ``dt`` apart grows by
            ``(gyro_bias_sigma dt)^2 + sim_gyro_noise^2 dt + sim_bias_walk^2 dt^3 / 3`` (the yaw
            drift of a gyro without magnetometer; white noise and bias walk from the attitude
            noise settings), up to ``max_drift_deg``.
        max_drift_deg: the drift's standard deviation stops growing at this, degrees: the
            attitude filter's accelerometer correction bounds it as the camera turns (simulated
            attitude on the tuning seeds 0-4, 1,500 frames: RMS error per axis of the relative
            rotation 0.10° over 4 s, 0.32° over 15 s, 0.40° over 30 s, 0.37° over 45 s, where the
            unbounded model says 0.15°, 0.44°, 0.88°, 1.31°).
        acceptance_covariance: the edge covariances of the loop test (the pose graph is always
            optimised with the paper's, below). "eq19": the optimisation's own (the paper's).
            "jitter" (the default, beyond the paper): an odometry edge's translation variance is
            ``jitter_variance_scale`` times the jitter of the frames tracked against its first
            keyframe, per axis of its frame (the mean square of their positions' second
            differences over 6, the variance of white noise on the positions; consecutive matches
            share most of their error, so the edge errs by several times the jitter), or, with
            fewer than ``min_jitter_frames`` tracked frames, the paper's; every edge's x, y
            variance also carries the attitude's error over its span times the scene's median
            depth (``NISlam._information``); and a loop edge allows for a drift common to the
            odometry edges (``drift_per_metre``). Eq. (19) is the spread of the whole correlation
            response, widest at the keyframe rule's last match, and says nothing of that match's
            error (``scripts/bench_loops.py --only nees``; docs/results/nislam.md, "NI-SLAM loop acceptance").
        jitter_variance_scale: the square of how many times the frames' jitter an odometry
            edge errs by (calibrated by the normalised estimation error of odometry edges).
        min_jitter_frames: fewest tracked frames against a keyframe for the "jitter" variance.
        drift_per_metre: with "jitter", the loop test allows for a drift common to the odometry
            edges of ``drift_per_metre`` times the path along the keyframe chain between the
            loop's keyframes (standard deviation per axis), which independent edge covariances
            cannot carry. (Summed odometry edge errors of the
            tuning sequences, loops off: 0.2-0.8 % of the path on the synthetic ones with
            ground-truth attitude, 0.4-1.3 % with simulated attitude, 1.7-2.5 % on 7-Scenes.)
        translation_variance_scale: an edge's image-plane (x, y) translation variance is this
            times the correlation's Eq. (19) variance (calibrated by the normalised estimation
            error of odometry edges against ground truth, ``scripts/bench_loops.py --nees``).
        depth_variance_scale: an edge's depth (z) variance is this times the population variance
            of the matched pixels' depth differences (``kcc.depth_translation``; the variance of
            one pixel's difference, larger than that of their median).
        min_translation_sigma_m: floor of an edge's translation standard deviation, metres.
        proximity_candidates: besides the place-recognition candidates, verify this many of the
            keyframes nearest to a new keyframe in the pose graph (at least ``min_separation``
            older, within ``max_rotation_deg``, in-plane offset within ``proximity_radius``), its
            image centred on the graph's offset: a revisit is tried even where the appearance
            score stays under ``min_score``, and more so when good tracking makes few keyframes.
            The chi-square test decides as for any loop; 0 turns it off.
        proximity_radius: largest in-plane graph offset of a proximity candidate, as a fraction of
            the old keyframe's orthographic image half-height (``r_k H / 2``): the two images then
            share most of their content.
        local_window: when a keyframe is made, also register it (as a loop candidate is verified)
            against this many keyframes before its predecessor, add the edges that pass the same
            chi-square test on the window's graph and optimise the window; 0 turns it off.
        visual_rotation: with an inertial attitude (``imu``, ``simulated``), a verified loop's
            relative pose is refined over the old keyframe's fused map, rotation included
            (``kcc.refine_against_map``: depth and grey Gauss-Newton from the correlator's
            answer), and its edge carries that rotation with its covariance, so the graph can
            undo the heading the gyro drifted by (beyond the paper, which says the inertial
            rotation sometimes needs visual correction). A refinement that does not converge
            leaves the edge as verified. Ground-truth attitude is never refined.
        visual_rotation_sigma_deg: standard deviation per axis added to the refinement's own
            rotation covariance (which treats the points' errors as independent), degrees. Not a
            calibrated error: on real frame pairs of the tuning sequences the refinement's
            rotation errs 0.63-0.66° RMS (synthetic: 0.01-0.04°), but its rotation and
            translation err together, and a floor at the real figure (0.7) let the graph keep
            the refined translation with another rotation, which was worse on the tuning
            sequences (docs/results/nislam.md, "Loop rotation measured").
    """

    enabled: bool = True
    orb_features: int = 1000
    min_separation: int = 3
    top_k: int = 5
    min_score: float = 0.05
    min_psr: float = 30.0
    min_matched: float = 0.1
    max_rotation_deg: float = 30.0
    chi2_quantile: float = 0.999
    max_odometry_bend_m: float = math.inf
    rotation_sigma_deg: float = 0.09
    groundtruth_rotation_sigma_deg: float = 0.01
    gyro_bias_sigma: float = ImuNoise.gyro_bias_init
    max_drift_deg: float = 0.5
    acceptance_covariance: AcceptanceCovariance = AcceptanceCovariance.JITTER
    jitter_variance_scale: float = 100.0
    min_jitter_frames: int = 5
    drift_per_metre: float = 0.01
    translation_variance_scale: float = 1.0
    depth_variance_scale: float = 1.0
    min_translation_sigma_m: float = 0.002
    proximity_candidates: int = 1
    proximity_radius: float = 0.5
    local_window: int = 0
    visual_rotation: bool = True
    visual_rotation_sigma_deg: float = 0.1

    LIMITS: ClassVar[dict[str, Limit]] = {
        "orb_features": AT_LEAST_1, "min_separation": AT_LEAST_1, "top_k": AT_LEAST_1, "min_score": NON_NEGATIVE,
        "min_psr": NON_NEGATIVE, "min_matched": FRACTION, "max_rotation_deg": Limit(ge=0, le=180),
        "chi2_quantile": Limit(gt=0, lt=1), "max_odometry_bend_m": Limit(gt=0, allow_inf=True),
        "rotation_sigma_deg": POSITIVE, "groundtruth_rotation_sigma_deg": POSITIVE, "gyro_bias_sigma": NON_NEGATIVE, "max_drift_deg": Limit(ge=0, allow_inf=True),
        "translation_variance_scale": POSITIVE, "depth_variance_scale": POSITIVE, "min_translation_sigma_m": POSITIVE,
        "jitter_variance_scale": POSITIVE, "min_jitter_frames": Limit(ge=3), "drift_per_metre": NON_NEGATIVE,
        "proximity_candidates": NON_NEGATIVE, "proximity_radius": POSITIVE, "local_window": NON_NEGATIVE,
        "visual_rotation_sigma_deg": POSITIVE,
    }

    def __post_init__(self) -> None:
        check_limits(self)
        object.__setattr__(self, "acceptance_covariance", parse_choice(AcceptanceCovariance, self.acceptance_covariance, "acceptance_covariance"))


@dataclass(frozen=True)
class NISlamConfig:
    """Settings of NI-SLAM. Defaults are the paper's where it gives them (σ, λ, T_c, T_d, T_K, T_M).

    Attributes:
        attitude: where rotations come from: "imu" (the sequence's IMU through the AHRS: the
            synthetic sequence's, or a TUM-layout folder's ``imu.txt``),
            "simulated" (gyro + accelerometer simulated on ground truth with noise and bias
            drift, then the same AHRS), "groundtruth" (what the NI-SLAM authors fed on TUM,
            which has no gyroscope), or "auto" (imu where the sequence has an IMU stream, else
            simulated).
        gravity: world direction of gravity for the simulated attitude; "auto" takes the world
            axis closest to the mean camera-down direction of the ground truth.
        sim_gyro_noise: simulated gyro white noise density, rad/s/sqrt(Hz).
        sim_bias_walk: simulated gyro bias random walk, rad/s^2/sqrt(Hz).
        sim_seed: seed of the simulated IMU noise.
        attitude_max_gap: a frame whose attitude would be interpolated across a larger gap of
            the stream is not tracked (counted in ``metrics.json``), seconds.
        attitude_time_offset: the attitude of an image stamped ``t`` is the stream's sample at
            ``t + attitude_time_offset``, seconds: the two clocks' offset, which
            ``torchslam calibrate-time`` estimates from the images and the stream's rotations
            (``torchslam calibrate-time``). Trajectories keep the image stamps.
        accel_compensation: with an attitude from the attitude filter (``imu``, ``simulated``),
            run its tilt correction again as frames are tracked, the accelerometer corrected by
            the camera's acceleration fitted to the tracked positions
            (``imu.AccelerationCompensation``; beyond the paper): the body's own acceleration
            otherwise leaks into the gravity direction and tilts the attitude by up to a degree.
            No effect with ground-truth attitude.
        accel_window: half width ``h`` of that fit, frames: a quadratic through the positions of
            ``2 h + 1`` frames centred on each (the correction runs ``h + 1`` frames behind).
        pixel_stride: use every n-th pixel in x and y of the depth image (1 = all; 2 quarters
            the projection cost).
        min_valid_points: frames with fewer valid depth points are not tracked.
        max_jump_m: a frame whose position departs from the constant-velocity prediction by
            more than this is treated like a PSR collapse (beyond the paper: a false
            correlation peak can score just above T_K while the true peak fades); ``inf``
            turns the test off. A match above ``kcc.T_M`` (one good enough to be fused) is
            trusted over the prediction and not tested.
        lost_uses_prior: a frame that is lost (PSR < T_K or no depth match) even against the
            fresh keyframe made from the last well-tracked frame takes the constant-velocity
            prediction as its position instead of its own correlation estimate, and starts the
            next keyframe there (beyond the paper; off: only implausible jumps do): a lost
            frame's own estimate would otherwise carry its error into every later keyframe.
        lost_agree_m: with ``lost_uses_prior``, a frame lost only for its PSR (its depth
            matched) keeps its own estimate where that lies within this distance of the
            prediction, metres (0: never; beyond the paper): the two agree, and a correct peak is
            measured to millimetres where the prediction carries the velocity's error.
        center_on_prediction: centre each frame's orthographic image on the constant-velocity
            prediction of its translation from the keyframe instead of on its own optical axis
            (beyond the paper; ``track_step``'s ``center``): the correlation then measures only
            the prediction's error, and the image borders, which stay put while the content
            moves, no longer pull the estimate towards the keyframe (a bias of 4–13 % of the
            shift on real frame pairs, ``scripts/bench_window.py``). Frames without a prediction
            (the first two, after a loop) and place-recognition loop candidates are centred on
            their axis; proximity candidates (``loop.proximity_candidates``) on the graph's offset.
        grey_at_depth_time: where the depth image was taken at another instant than the colour
            image (``Frame.depth_timestamp``), sample each point's grey value where the point
            appears in the colour image after the attitude stream's rotation between the two
            instants (``sample_grey``). The geometry, and the attitude that rotates it, are
            always taken at the depth instant.
        undistort: where the sequence camera has lens distortion (``PinholeCamera.distortion``,
            e.g. the TUM freiburg1/2 presets), back-project each pixel along its undistorted ray
            and sample the colour image through the forward distortion; off treats the images
            as ideal pinhole images. Cameras without distortion are unaffected.
        prepare_ahead: in ``run_sequence``, each frame's attitude look-up and back-projection
            (the ``backproject`` stage) run on a thread of their own while the frames before it
            are tracked (``systems.base.AheadFrames``): the same results, overlapped with
            tracking where a core is free. False: done inline by ``track``.
        prepare_ahead_in: where that work and the reading of the frames run: ``"process"``, a
            child process forked after ``start`` (on the CPU where the fork start method exists;
            elsewhere the thread), which shares no interpreter lock with tracking
            (``systems.ahead_process``), or ``"thread"`` (the default here: a frame's input
            and back-projected cloud cost more to copy between the processes than the lock's
            hand-overs cost tracking; docs/results/cpu.md, "Frames read and prepared in a child process").
            The same results either way.
        kcc: correlator, keyframe and fusion settings. The paper's values except
            ``depth_median_center``, on here: with the paper's depth test, any motion along the
            optical axis of more than ``T_d`` (10 cm) since the keyframe matches no pixel, which
            breaks tracking on hand-held sequences; and ``depth_statistic``, "median" here
            (``depth_translation``); and ``masked_kernel``, on here: the kernel distance over the
            pixels both images hold, so the sensor's holes, which move with the camera, do not
            pull each match towards no motion (docs/results/nislam.md#masked-kernel-windows). ``kcc.T_K`` and
            ``kcc.T_M`` are read, with ``max_jump_m``,
            ``lost_uses_prior`` and ``lost_agree_m``, by the keyframe policy (``policy.KeyframePolicy``).
        loop: loop closure settings.
        map_voxel: voxel size of ``map.ply``, metres.
        monitor_images_every: log the orthographic image of every n-th keyframe and the
            correlation response of the first frame matched against it (TensorBoard).

    Every numeric field has a declared ``Limit`` (``LIMITS``); NaN is refused everywhere.
    """

    attitude: AttitudeSource = AttitudeSource.AUTO
    gravity: Gravity = Gravity.AUTO
    sim_gyro_noise: float = ImuNoise.gyro_noise_density
    sim_bias_walk: float = ImuNoise.gyro_bias_walk
    sim_seed: int = 0
    attitude_max_gap: float = 0.1
    attitude_time_offset: float = 0.0
    accel_compensation: bool = True
    accel_window: int = 5
    pixel_stride: int = 1
    min_valid_points: int = 1000
    max_jump_m: float = 0.1
    lost_uses_prior: bool = True
    lost_agree_m: float = 0.02
    center_on_prediction: bool = True
    grey_at_depth_time: bool = True
    undistort: bool = True
    prepare_ahead: bool = True
    prepare_ahead_in: str = "thread"
    kcc: KCCConfig = field(
        default_factory=lambda: KCCConfig(depth_median_center=True, depth_statistic="median", frame_taper=24, masked_kernel=True)
    )
    loop: LoopConfig = field(default_factory=LoopConfig)
    map_voxel: float = 0.01
    monitor_images_every: int = 10

    LIMITS: ClassVar[dict[str, Limit]] = {
        "sim_gyro_noise": NON_NEGATIVE, "sim_bias_walk": NON_NEGATIVE, "sim_seed": Limit(),
        "attitude_max_gap": POSITIVE, "attitude_time_offset": Limit(), "accel_window": Limit(ge=2),
        "pixel_stride": AT_LEAST_1,
        "min_valid_points": AT_LEAST_1, "max_jump_m": Limit(gt=0, allow_inf=True),
        "lost_agree_m": NON_NEGATIVE, "map_voxel": POSITIVE,
        "monitor_images_every": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        check_limits(self)
        if self.prepare_ahead_in not in ("process", "thread"):
            raise ConfigError(f"prepare_ahead_in: expected 'process' or 'thread', got {self.prepare_ahead_in!r}")
        object.__setattr__(self, "attitude", parse_choice(AttitudeSource, self.attitude, "attitude"))
        object.__setattr__(self, "gravity", parse_choice(Gravity, self.gravity, "gravity"))
