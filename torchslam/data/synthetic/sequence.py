"""Synthetic RGB-D-inertial sequences: settings, the lazily rendered sequence and its TUM folder writer.

A sequence renders the room of ``scene`` with ``render`` along a trajectory of ``motion``; an
IMU (gyroscope and accelerometer with white noise and bias random walk,
:class:`torchslam.imu.ImuNoise`) is simulated from the analytic trajectory and run through the
attitude filter of :mod:`torchslam.imu`.

Convention:
    World frame: z up, gravity ``(0, 0, -gravity)``. Camera frame: x right, y down, z forward
    (OpenCV); poses are camera-to-world ``T_wc``. The IMU frame is the camera frame (identity
    extrinsics).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, ClassVar, Iterator

import numpy as np
import torch
from torch import Tensor

from ...errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, FieldError, Limit, check_limits, parse_choice
from ...geometry import PinholeCamera, se3_from_Rt
from ...imu import AttitudeStream, ImuData, ImuNoise, Kinematics, ahrs_attitude, simulate_imu
from ..calibration import DEPTH_SCALE_RANGE, READOUT_KEYWORD, intrinsics_problem
from ..frame import Frame, Sequence
from ..trajectory import Trajectory, write_tum_trajectory
from .motion import SyntheticTrajectory, trajectory_kinematics, trajectory_pose
from .render import SceneRenderer, kinect_depth_noise
from .scene import _generator, _sub_seed, build_scene

__all__ = [
    "TUM_FOLDER_ENTRIES",
    "SyntheticConfig",
    "SyntheticSequence",
    "camera_from_config",
    "generate_sequence",
    "synthetic_kinematics",
    "synthetic_trajectory",
    "write_tum_folder",
]

logger = logging.getLogger(__name__)

# TUM freiburg1 colour intrinsics at 640 x 480.
_FR1 = (517.3, 516.5, 318.6, 255.3, 640, 480)


@dataclass(frozen=True)
class SyntheticConfig:
    """Settings of a synthetic RGB-D-inertial sequence.

    Attributes:
        frames: number of frames.
        width, height: image size, pixels.
        fps: frame rate, Hz; frame k is at ``k / fps`` seconds.
        seed: seeds the scene layout, textures, hand-held shake, depth noise and IMU noise.
        trajectory: the camera motion (``SyntheticTrajectory``; its name in configs): "orbit"
            (rotation-dominant), "translate" (translation-dominant), "loop" (returns to its
            start every period: for loop closure), "handheld" (a slow pan with hand-held shake).
        period: duration of one cycle of the trajectory, seconds (default 10 s = 300 frames at
            30 Hz, so the default "loop" closes at its last frame).
        fx, fy, cx, cy: intrinsics in pixels; None takes TUM freiburg1's scaled to the size.
        depth_noise: apply the Kinect-like noise model to depth.
        depth_noise_k: k in sigma_z = k z^2, 1/m (Kinect v1: about 0.0012 to 0.0019).
        depth_holes: fraction of pixels whose depth is dropped (set to 0) at random.
        depth_scale: depth quantisation, steps per metre (TUM: 5000, i.e. 0.2 mm steps); also
            the scale of the 16-bit depth PNGs ``write_tum_folder`` writes.
        max_depth: depth beyond this is invalid (0), metres.
        imu_rate: IMU sample rate, Hz.
        imu_noise: noise of the simulated IMU (``ImuNoise``; in configs the section
            ``imu_noise``, or its six fields flat, ``data.synthetic.gyro_noise_density=...``).
        gravity: magnitude of gravity, m/s^2 (pointing to world -z).
        attitude_time_constant: tilt-correction time constant of the attitude filter, seconds.
        texture_density: texels per metre of the surface textures.
        batch_size: frames rendered together when iterating or writing.
        exposure: the colour camera's exposure time, seconds (0: none, sharp images). A frame's
            colour is the mean of ``exposure_samples`` renders at instants spread evenly over
            ``[t - exposure / 2, t + exposure / 2]`` along the trajectory (motion blur); its
            depth and ground-truth pose stay those of the frame time ``t``.
        exposure_samples: renders averaged per frame when ``exposure > 0`` (at least 2).
        depth_stamp_jitter: the depth stream's stamps as an unsynchronised sensor's: depth image
            ``k`` is stamped ``k / fps + u_k`` with ``u_k`` uniform in ``[-jitter, jitter]``
            seconds (seeded; TUM fr1 pairs colour and depth up to 17 ms apart); 0 stamps both
            images alike. Less than half a frame period.
        depth_time_offset: the depth image is taken at its stamp plus this, seconds (a planted
            latency of the depth stream, as ``data.depth_time_offset`` models it); its pixels
            are rendered from the pose at that instant.
        readout_time: a planted rolling shutter, seconds from the first image row to the last
            (0: a global shutter). Both images are read top row first, their stamps at the middle
            row: rows are rendered in bands of 16, each band from the pose at its middle row's
            instant (within ``readout_time`` / 64 of each row's own, for 480 rows), as
            GC-SLAM's ``readout_time`` models it. The ground truth stays at the stamps.
    """

    frames: int = 300
    width: int = 640
    height: int = 480
    fps: float = 30.0
    seed: int = 0
    trajectory: SyntheticTrajectory = SyntheticTrajectory.ORBIT
    period: float = 10.0
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    depth_noise: bool = True
    depth_noise_k: float = 0.0015
    depth_holes: float = 0.01
    depth_scale: float = 5000.0
    max_depth: float = 10.0
    imu_rate: float = 200.0
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    gravity: float = 9.81
    attitude_time_constant: float = 10.0
    texture_density: float = 128.0
    batch_size: int = 8
    exposure: float = 0.0
    exposure_samples: int = 8
    depth_stamp_jitter: float = 0.0
    depth_time_offset: float = 0.0
    readout_time: float = 0.0

    LIMITS: ClassVar[dict[str, Limit]] = {
        "frames": AT_LEAST_1, "width": AT_LEAST_1, "height": AT_LEAST_1, "fps": POSITIVE, "seed": Limit(),
        "period": POSITIVE, "fx": POSITIVE, "fy": POSITIVE, "cx": Limit(), "cy": Limit(), "depth_noise_k": NON_NEGATIVE,
        "depth_holes": Limit(ge=0, lt=1), "depth_scale": Limit(ge=DEPTH_SCALE_RANGE[0], le=DEPTH_SCALE_RANGE[1]),
        "max_depth": POSITIVE, "imu_rate": POSITIVE, "gravity": POSITIVE, "attitude_time_constant": Limit(gt=0, allow_inf=True),
        "texture_density": Limit(gt=0, le=1024), "batch_size": AT_LEAST_1, "exposure": NON_NEGATIVE,
        "exposure_samples": Limit(ge=2), "depth_stamp_jitter": Limit(ge=0, le=0.05),
        "depth_time_offset": Limit(ge=-0.5, le=0.5), "readout_time": Limit(ge=0, le=0.1),
    }
    # Config keys of earlier releases, read as the nested fields they became.
    ALIASES: ClassVar[dict[str, str]] = {f.name: f"imu_noise.{f.name}" for f in fields(ImuNoise)}

    def __post_init__(self) -> None:
        def fail(key: str, expected: str) -> None:
            raise ConfigError(f"SyntheticConfig.{key}: expected {expected}, got {getattr(self, key)!r}")

        check_limits(self)
        object.__setattr__(self, "trajectory", parse_choice(SyntheticTrajectory, self.trajectory, "SyntheticConfig.trajectory"))
        if not isinstance(self.imu_noise, ImuNoise):
            fail("imu_noise", "an ImuNoise")
        if not isinstance(self.depth_noise, bool):
            fail("depth_noise", "true or false")
        if self.depth_stamp_jitter >= 0.5 / self.fps:
            fail("depth_stamp_jitter", f"less than half a frame period ({0.5 / self.fps:g} s at {self.fps:g} Hz), so that the depth stamps increase")
        if self.max_depth * self.depth_scale > 65535:
            fail("max_depth", f"at most {65535 / self.depth_scale:.3f} m so depth fits 16-bit PNGs at depth_scale")
        # The same plausibility test as a calibration.txt (calibration.intrinsics_problem).
        cam = camera_from_config(self)
        problem = intrinsics_problem(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, self.depth_scale)
        if problem is not None:
            raise FieldError(*problem, owner=type(self).__name__)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """Return the names of all settings."""
        return tuple(f.name for f in fields(cls))


def camera_from_config(cfg: SyntheticConfig) -> PinholeCamera:
    """Return the camera of ``cfg``: explicit intrinsics, or TUM freiburg1's scaled to the image size."""
    fx0, fy0, cx0, cy0, w0, h0 = _FR1
    sx, sy = cfg.width / w0, cfg.height / h0
    # Pixel centres sit at integers, so scale about the image edge at -0.5.
    return PinholeCamera(
        fx=float(cfg.fx) if cfg.fx is not None else fx0 * sx,
        fy=float(cfg.fy) if cfg.fy is not None else fy0 * sy,
        cx=float(cfg.cx) if cfg.cx is not None else (cx0 + 0.5) * sx - 0.5,
        cy=float(cfg.cy) if cfg.cy is not None else (cy0 + 0.5) * sy - 0.5,
        width=cfg.width,
        height=cfg.height,
    )


def synthetic_trajectory(cfg: SyntheticConfig) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """Return the analytic camera motion of ``cfg`` as a function of time (``motion.trajectory_pose``).

    The function maps (M,) float64 times (seconds) to ``R_wc`` (M, 3, 3) and camera centres
    (M, 3) in metres.
    """
    return trajectory_pose(cfg.trajectory, cfg.period, cfg.seed)


def synthetic_kinematics(cfg: SyntheticConfig, times: Tensor) -> Kinematics:
    """Exact motion of the synthetic camera (= IMU) of ``cfg`` at (M,) float64 ``times``, seconds.

    Acceleration and angular rate come from automatic differentiation of the analytic
    trajectory (``motion.trajectory_kinematics``).
    """
    return trajectory_kinematics(synthetic_trajectory(cfg), times)


class SyntheticSequence(Sequence):
    """A synthetic RGB-D-inertial sequence (implements the ``Sequence`` protocol).

    Frames are rendered lazily: indexing renders the batch of ``cfg.batch_size`` frames holding
    the index and keeps it, so sequential access runs at batched speed; iteration renders batch
    by batch. Depth noise of frame i is drawn from a generator seeded by (seed, i), so a frame is
    the same however it was reached.

    Attributes:
        name: "synthetic-<trajectory>-seed<seed>".
        camera: intrinsics and size.
        timestamps: (N,) float64 frame times ``k / fps``, seconds.
        groundtruth: exact camera-to-world poses at the frame times.
        imu: simulated IMU stream (IMU frame = camera frame) from t = 0 to (at least) the last frame.
        imu_gyro_bias, imu_accel_bias: (M, 3) float64 true biases of that stream.
        attitude: AHRS attitude from ``imu`` (source "imu"), started at the true first attitude.
        scene: the rendered scene.
        gravity_w: (3,) float64 gravity in the world frame, m/s^2.
        readout_time: the planted rolling shutter, ``cfg.readout_time`` (``readout_source``
            "synthetic" where it is not 0).
    """

    def __init__(self, cfg: SyntheticConfig | None = None, device: torch.device | str | None = None):
        cfg = SyntheticConfig() if cfg is None else cfg
        self.cfg = cfg
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.name = f"synthetic-{cfg.trajectory}-seed{cfg.seed}"
        self.readout_time = float(cfg.readout_time)
        self.readout_source = "synthetic" if cfg.readout_time > 0 else None
        self.camera = camera_from_config(cfg)
        self.timestamps = torch.arange(cfg.frames, dtype=torch.float64) / cfg.fps
        pose = self._pose = synthetic_trajectory(cfg)
        R, p = pose(self.timestamps)
        self.groundtruth = Trajectory(self.timestamps, se3_from_Rt(R, p))
        jitter = torch.rand(cfg.frames, generator=_generator(_sub_seed(cfg.seed, 6), "cpu"), dtype=torch.float64)
        # The depth stream's stamps (the colour ones unless ``depth_stamp_jitter``) and the
        # instants its images are taken at (``depth_time_offset`` after them).
        self.depth_timestamps = self.timestamps + (2.0 * jitter - 1.0) * cfg.depth_stamp_jitter
        self._depth_instants = self.depth_timestamps + cfg.depth_time_offset
        self.gravity_w = torch.tensor([0.0, 0.0, -cfg.gravity], dtype=torch.float64)
        t_end = float(self.timestamps[-1])
        # IMU samples k / imu_rate from 0 up to the first sample at or after the last frame.
        imu_times = torch.arange(int(math.ceil(t_end * cfg.imu_rate - 1e-9)) + 1, dtype=torch.float64) / cfg.imu_rate
        sim = simulate_imu(synthetic_kinematics(cfg, imu_times), cfg.imu_noise, self.gravity_w, _sub_seed(cfg.seed, 3))
        self.imu: ImuData = sim.imu
        self.imu_gyro_bias, self.imu_accel_bias = sim.gyro_bias, sim.accel_bias
        self.attitude: AttitudeStream = ahrs_attitude(
            self.imu, R[0], time_constant=cfg.attitude_time_constant, gravity=cfg.gravity
        )
        self.scene = build_scene(cfg.seed, cfg.texture_density, self.device)
        self.renderer = SceneRenderer(self.scene, self.camera, self.device)
        # readout_time: (first row, end row, seconds after the stamp, renderer of those rows) per band.
        self._bands: list[tuple[int, int, float, SceneRenderer]] = []
        if cfg.readout_time > 0:
            H = self.camera.height
            for r0 in range(0, H, _BAND_ROWS):
                r1 = min(H, r0 + _BAND_ROWS)
                cam = PinholeCamera(self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy - r0, self.camera.width, r1 - r0)
                delta = cfg.readout_time * ((r0 + r1 - 1) / 2 - (H - 1) / 2) / H
                self._bands.append((r0, r1, delta, SceneRenderer(self.scene, cam, self.device)))
        self._cached: tuple[int, Tensor, Tensor] | None = None

    def __len__(self) -> int:
        return self.cfg.frames

    def render(self, indices: Tensor | list[int] | range) -> tuple[Tensor, Tensor]:
        """Render frames by index (no caching).

        Args:
            indices: (B,) frame indices.

        Returns:
            rgb: (B, 3, H, W) float32 in [0, 1] (motion-blurred over ``cfg.exposure``); depth:
            (B, 1, H, W) float32 metres, 0 = invalid (noisy if ``cfg.depth_noise``).
        """
        idx = torch.as_tensor(list(indices) if not isinstance(indices, Tensor) else indices, dtype=torch.int64)
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= len(self)):
            raise IndexError(f"indices: frame index out of range 0..{len(self) - 1}")
        cfg = self.cfg
        if self._bands and idx.numel():
            rgb, depth = self._rolling(idx)
        else:
            out = self.renderer.render(self.groundtruth.T_wc[idx])
            depth = out.depth
            if idx.numel() and bool((self._depth_instants[idx] != self.timestamps[idx]).any()):
                R, p = self._pose(self._depth_instants[idx])
                depth = self.renderer.render(se3_from_Rt(R, p)).depth
            rgb = out.rgb if cfg.exposure <= 0 or not idx.numel() else self._exposed(idx)
        if cfg.depth_noise:
            # One generator per frame so noise does not depend on how frames were batched.
            depth = torch.stack(
                [
                    kinect_depth_noise(
                        depth[j],
                        cfg.depth_noise_k,
                        cfg.depth_holes,
                        cfg.depth_scale,
                        _generator(_sub_seed(cfg.seed, 4, int(i)), self.device),
                        cfg.max_depth,
                    )
                    for j, i in enumerate(idx.tolist())
                ]
            ) if idx.numel() else depth
        else:
            depth = torch.where(depth <= cfg.max_depth, depth, torch.zeros_like(depth))
        return rgb, depth

    def _exposed(self, idx: Tensor, delta: float = 0.0, renderer: SceneRenderer | None = None) -> Tensor:
        """(B, 3, H, W) colour of frames ``idx`` averaged over their exposure (``cfg.exposure``),
        ``delta`` seconds after the stamps, by ``renderer`` (the whole image's by default)."""
        cfg = self.cfg
        renderer = renderer or self.renderer
        n = cfg.exposure_samples
        rgb = None
        for k in range(n):  # one render of the whole batch per instant of the exposure
            t = self.timestamps[idx] + delta + cfg.exposure * (k / (n - 1) - 0.5)
            R, p = self._pose(t)
            sub = renderer.render(se3_from_Rt(R, p)).rgb
            rgb = sub if rgb is None else rgb.add_(sub)
        return rgb.div_(n)

    def _rolling(self, idx: Tensor) -> tuple[Tensor, Tensor]:
        """(B, 3, H, W) colour and (B, 1, H, W) noise-free depth of frames ``idx`` read by a rolling
        shutter (``cfg.readout_time``): each band of rows rendered at its own instant."""
        cam, B = self.camera, idx.numel()
        rgb = torch.empty(B, 3, cam.height, cam.width, device=self.device)
        depth = torch.empty(B, 1, cam.height, cam.width, device=self.device)
        same = bool((self._depth_instants[idx] == self.timestamps[idx]).all())
        for r0, r1, delta, renderer in self._bands:
            R, p = self._pose(self.timestamps[idx] + delta)
            out = renderer.render(se3_from_Rt(R, p))
            rgb[:, :, r0:r1] = out.rgb if self.cfg.exposure <= 0 else self._exposed(idx, delta, renderer)
            if same:
                depth[:, :, r0:r1] = out.depth
            else:
                R, p = self._pose(self._depth_instants[idx] + delta)
                depth[:, :, r0:r1] = renderer.render(se3_from_Rt(R, p)).depth
        return rgb, depth

    def _frame(self, i: int, rgb: Tensor, depth: Tensor) -> Frame:
        t, t_d = float(self.timestamps[i]), float(self.depth_timestamps[i])
        return Frame(index=i, timestamp=t, rgb=rgb, depth=depth, T_wc=self.groundtruth.T_wc[i],
                     depth_timestamp=None if t_d == t else t_d)

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"index: expected an int, got {type(index).__name__}")
        i = int(index) + n if index < 0 else int(index)
        if not 0 <= i < n:
            raise IndexError(f"index: {index} out of range for {n} frames")
        bs = self.cfg.batch_size
        start = (i // bs) * bs
        if self._cached is None or self._cached[0] != start:
            rgb, depth = self.render(range(start, min(start + bs, n)))
            self._cached = (start, rgb, depth)
        _, rgb, depth = self._cached
        # Copies, so a consumer writing into its frame cannot alter the cached batch.
        return self._frame(i, rgb[i - start].clone(), depth[i - start].clone())

    def __iter__(self) -> Iterator[Frame]:
        bs = self.cfg.batch_size
        for start in range(0, len(self), bs):
            stop = min(start + bs, len(self))
            rgb, depth = self.render(range(start, stop))
            for j in range(stop - start):
                yield self._frame(start + j, rgb[j], depth[j])


# Rows of a band rendered at one instant under ``readout_time`` (the renderer's tile height).
_BAND_ROWS = 16


def generate_sequence(cfg: SyntheticConfig | None = None, device: torch.device | str | None = None) -> SyntheticSequence:
    """Build a synthetic sequence (scene, trajectory, IMU, attitude); frames render on access.

    Args:
        cfg: settings (defaults if None).
        device: where scene and images live (CPU if None).
    """
    return SyntheticSequence(cfg, device)


# What ``write_tum_folder`` writes, and the comment its calibration.txt (written first) starts with.
TUM_FOLDER_ENTRIES = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "calibration.txt", "imu.txt")
_CALIBRATION_MARK = "# fx fy cx cy depth_scale width height   (torchslam synthetic pinhole camera"


def _prepare_tum_folder(out: Path, overwrite: bool) -> None:
    """Make ``out`` an empty folder; with ``overwrite`` clear a folder that ``write_tum_folder`` wrote.

    A folder "looks written by torchslam" when it holds nothing but ``TUM_FOLDER_ENTRIES``, its
    ``rgb/`` and ``depth/`` hold only PNG files, and its ``calibration.txt`` (the first file the
    writer writes, so an interrupted write is recognised too) carries the writer's comment.
    Anything else is refused rather than deleted.
    """
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if not out.is_dir():
        return
    entries = sorted(out.iterdir())
    if not entries:
        return
    if not overwrite:
        raise ConfigError(
            f"{out}: folder is not empty ({len(entries)} entries); pass --overwrite (overwrite=True) to replace "
            "a sequence that torchslam synth wrote there, or choose a new folder"
        )
    foreign = [p.name for p in entries if p.name not in TUM_FOLDER_ENTRIES]
    foreign += [
        f"{sub}/{p.name}" for sub in ("rgb", "depth") if (out / sub).is_dir()
        for p in sorted((out / sub).iterdir()) if p.suffix != ".png" or not p.is_file()
    ]
    foreign += [name for name in ("rgb", "depth") if (out / name).exists() and not (out / name).is_dir()]
    calib = out / "calibration.txt"
    try:
        marked = calib.read_text(errors="replace").startswith(_CALIBRATION_MARK)
    except OSError:
        marked = False
    if foreign or not marked:
        why = f"it holds {', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}" if foreign else (
            "its calibration.txt was not written by torchslam synth")
        raise ConfigError(
            f"{out}: not cleared for --overwrite: {why}; only an empty folder or a sequence folder that "
            "torchslam synth wrote is replaced"
        )
    for p in entries:
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()
    logger.info("cleared %s (%d entries) to write a new sequence", out, len(entries))


def write_tum_folder(seq: SyntheticSequence, out_dir: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a synthetic sequence as a TUM RGB-D folder.

    Layout: ``rgb/<t>.png`` (8-bit colour), ``depth/<t>.png`` (16-bit, metres x depth_scale,
    0 = invalid), ``rgb.txt`` and ``depth.txt`` (``timestamp path``), ``groundtruth.txt``
    (``t tx ty tz qx qy qz qw``, camera-to-world), ``calibration.txt`` (``fx fy cx cy
    depth_scale width height``, and ``readout SECONDS`` for a planted rolling shutter) and ``imu.txt`` (``timestamp gx gy gz ax ay az``; rad/s and
    m/s^2 in the IMU frame, which is the camera frame). Timestamps are written with 6 decimals.
    ``torchslam.data.TUMSequence`` reads all of it back, ``imu.txt`` included.

    Args:
        seq: the sequence.
        out_dir: folder to create, or an empty folder.
        overwrite: replace the contents of a non-empty ``out_dir`` if it is a sequence folder this
            function wrote (nothing but its files, see ``TUM_FOLDER_ENTRIES``); anything else is
            refused.

    Returns:
        The folder path.

    Raises:
        ConfigError: ``out_dir`` is a file, or is not empty (without ``overwrite``, or with it
            when it does not look like a folder this function wrote).
    """
    import cv2  # only the writer needs OpenCV

    out = Path(out_dir)
    _prepare_tum_folder(out, overwrite)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    cfg, cam = seq.cfg, seq.camera
    (out / "calibration.txt").write_text(
        f"{_CALIBRATION_MARK}; raw/depth_scale = metres; 0 = invalid)\n"
        f"{cam.fx:.6f} {cam.fy:.6f} {cam.cx:.6f} {cam.cy:.6f} {cfg.depth_scale:g} {cam.width} {cam.height}\n"
        # A planted rolling shutter is the sensor's: GC-SLAM's readout_time=auto reads it back.
        + (f"{READOUT_KEYWORD} {cfg.readout_time!r}\n" if cfg.readout_time > 0 else "")
    )
    stamps = [f"{float(t):.6f}" for t in seq.timestamps]
    depth_stamps = [f"{float(t):.6f}" for t in seq.depth_timestamps]
    bs = cfg.batch_size
    for start in range(0, len(seq), bs):
        stop = min(start + bs, len(seq))
        rgb, depth = seq.render(range(start, stop))
        rgb8 = (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        raw = (depth[:, 0] * cfg.depth_scale).round().clamp(0, 65535).cpu().numpy().astype(np.uint16)
        for j in range(stop - start):
            name = stamps[start + j] + ".png"
            if not cv2.imwrite(str(out / "rgb" / name), np.ascontiguousarray(rgb8[j][:, :, ::-1])):
                raise OSError(f"{out / 'rgb' / name}: could not write PNG")
            name = depth_stamps[start + j] + ".png"
            if not cv2.imwrite(str(out / "depth" / name), raw[j]):
                raise OSError(f"{out / 'depth' / name}: could not write PNG")
    source = f"torchslam synthetic sequence {seq.name} ({cfg.frames} frames, {cfg.width}x{cfg.height})"
    for kind, title, kind_stamps in (("rgb", "color images", stamps), ("depth", "depth maps", depth_stamps)):
        lines = [f"# {title}", f"# file: '{source}'", "# timestamp filename"]
        lines += [f"{s} {kind}/{s}.png" for s in kind_stamps]
        (out / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    write_tum_trajectory(out / "groundtruth.txt", seq.groundtruth, header=f"ground truth trajectory\nfile: '{source}'")
    imu = seq.imu
    rows = torch.cat([imu.timestamps[:, None], imu.gyro, imu.accel], dim=1).tolist()
    lines = [
        "# imu data",
        f"# file: '{source}'",
        "# gyro rad/s, accel m/s^2 (specific force), IMU frame = camera frame (x right, y down, z forward)",
        "# world gravity (0, 0, -g): a camera at rest measures accel = R_wc^T (0, 0, g)",
        "# timestamp gx gy gz ax ay az",
    ]
    lines += [f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) for r in rows]
    (out / "imu.txt").write_text("\n".join(lines) + "\n")
    logger.info("wrote %d frames of %s to %s", len(seq), seq.name, out)
    return out
