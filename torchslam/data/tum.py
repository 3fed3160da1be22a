"""TUM RGB-D sequence reader: list parsing, rgb-depth association, ground truth, lazy decoding.

A TUM RGB-D folder holds ``rgb.txt`` and ``depth.txt`` (lines ``timestamp path``, paths relative
to the folder), optionally ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world),
``accelerometer.txt`` (``timestamp ax ay az``, m/s^2), ``calibration.txt`` (see
``torchslam.data.calibration``) and ``imu.txt`` (below). Lines starting with ``#`` and blank
lines are skipped.

``imu.txt`` is an IMU stream, one sample a line: ``timestamp gx gy gz ax ay az``, seconds, the
angular rate in rad/s and the specific force in m/s^2, both in the camera frame (x right, y down,
z forward; the IMU is taken to be aligned with the camera), with the sign an accelerometer
measures: at rest it reads +g along the camera's *up* direction, ``R_wc^T (0, 0, 9.81)`` in a
z-up world. ``torchslam synth`` writes this file. The stream is exposed as ``imu`` and, through
the attitude filter of ``torchslam.imu.ahrs_attitude``, as ``attitude`` (source "imu"), as the
synthetic sequence exposes its own; NI-SLAM's ``attitude=imu`` (and ``auto``) use it. Like the
in-memory synthetic sequence, the filter starts at the ground-truth rotation at the first IMU
sample where ``groundtruth.txt`` has one and its world is z-up (the filter's world; checked
against the up that the stream's first 10 s of specific force show, ``imu.start_up``);
otherwise it starts levelled by gravity (roll and pitch from that up) with zero yaw. Only the start fixes the world
frame: every rotation after it comes from the IMU alone.

Choices this reader makes:
    * Colour and depth stamps are paired one-to-one, closest pairs first, within ``max_gap``
      (0.02 s by default), which is the TUM benchmark's association rule (its ``associate.py``
      default). A frame keeps its colour timestamp.
    * Ground truth at a frame is interpolated between the two bracketing poses (linear in
      translation, SLERP in rotation) when they are at most ``gt_max_gap`` apart (0.2 s by
      default). That bridges the occasional dropped motion-capture samples of the 100 Hz TUM
      ground truth (fr1/xyz has a 110 ms hole) while keeping the interpolation error small: for a
      hand-held camera accelerating at 1 m/s^2 the constant-velocity error over 0.2 s is at most
      a T^2 / 8 = 5 mm. Frames outside the ground-truth span or inside a longer hole get none.
    * Raw depth values listed in ``invalid_depth`` (0 and 65535 by default; 7-Scenes marks holes
      with 65535) become 0 = invalid; the rest is divided by the depth scale to give metres.
    * PNGs of the common simple kind (8-bit RGB, 8/16-bit grey, rows filtered ``None`` or
      ``Sub``, as TUM RGB-D writes them) are decoded by ``png.decode_png`` (ISA-L's inflate,
      about 2.5x faster on fr1/xyz); every other image by OpenCV. The pixels are the same.
    * A colour or depth image that cannot be decoded (unreadable, truncated, not an image) is, during
      iteration, logged as a warning, skipped and recorded in ``skipped``; indexing it raises.
      An image that decodes but has the wrong size or pixel format raises in both cases, since
      it means the calibration or the folder is wrong rather than one frame.
"""

from __future__ import annotations

import logging
import math
import operator
import os
import queue
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError, DataFormatError
from ..geometry import PinholeCamera
from ..imu import AttitudeStream, ImuData, ahrs_attitude, start_up
from ..threads import name_os_thread
from .calibration import Calibration, colour_to_depth_maps, resolve_calibration
from .frame import Frame, associate_timestamps
from .png import available as png_available
from .png import decode_png
from .trajectory import Trajectory, read_tum_trajectory

__all__ = ["TUMSequence", "AssociationStats", "CorruptImageError", "ImageFormatError", "sequence_info"]

logger = logging.getLogger(__name__)

RGB_LIST = "rgb.txt"
DEPTH_LIST = "depth.txt"
GROUNDTRUTH_FILE = "groundtruth.txt"
ACCELEROMETER_FILE = "accelerometer.txt"
IMU_FILE = "imu.txt"

# Largest angle between the ground truth's world up and the up the IMU's specific force shows at
# the start (``imu.start_up``, averaged over seconds) for the ground truth to start the attitude
# filter (the motion's own acceleration and the gyro's bias leave about a degree; a world that is
# not z-up is tens of degrees off).
_IMU_START_MAX_TILT_DEG = 20.0

# Range of the median specific-force magnitude, m/s^2, that ``imu.txt`` may show (gravity is 9.81).
_IMU_GRAVITY_RANGE = (4.9, 19.6)

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8"
# End markers are searched for in the file's tail so that a few bytes of padding are tolerated.
_TAIL_BYTES = 64


class CorruptImageError(DataFormatError):
    """An image file of a sequence cannot be read or decoded (missing bytes, not an image)."""


class ImageFormatError(DataFormatError):
    """An image of a sequence decodes but has the wrong size or pixel format (e.g. 8-bit depth)."""


@dataclass(frozen=True)
class AssociationStats:
    """How colour and depth stamps were paired (before stride and range selection).

    Attributes:
        rgb_count: entries in ``rgb.txt``.
        depth_count: entries in ``depth.txt``.
        pairs: associated colour-depth pairs.
        dropped_rgb: colour entries left without a depth partner.
        dropped_depth: depth entries left without a colour partner.
        max_gap_s: largest |t_rgb - t_depth| among the pairs, seconds.
        mean_gap_s: mean |t_rgb - t_depth| among the pairs, seconds.
        max_gap_allowed_s: the association threshold used, seconds.
        mean_depth_minus_colour_s: mean signed ``t_depth - t_rgb`` among the pairs, seconds (as
            written, before ``depth_time_offset``): a stream stamped consistently before or after
            the other shows here (TUM fr1/xyz: -0.011).
    """

    rgb_count: int
    depth_count: int
    pairs: int
    dropped_rgb: int
    dropped_depth: int
    max_gap_s: float
    mean_gap_s: float
    max_gap_allowed_s: float
    mean_depth_minus_colour_s: float = 0.0


def _read_stamped_list(path: Path, columns: str) -> tuple[np.ndarray, list[list[str]], list[int]]:
    """Parse ``timestamp value...`` lines; check the count, numbers and strictly increasing stamps.

    Args:
        path: the list file.
        columns: the expected line layout, e.g. ``"timestamp filename"``; its word count is the
            number of fields per line.

    Returns:
        timestamps: (N,) float64 seconds.
        fields: the remaining fields of each line as strings.
        lines: 1-based line numbers of the entries.
    """
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: cannot read ({exc})") from exc
    n_fields = len(columns.split())
    stamps: list[float] = []
    fields: list[list[str]] = []
    lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != n_fields:
            raise DataFormatError(f"{path}:{lineno}: expected {n_fields} values '{columns}', got {len(parts)}: {s!r}")
        try:
            t = float(parts[0])
        except ValueError as exc:
            raise DataFormatError(f"{path}:{lineno}: timestamp is not a number: {parts[0]!r}") from exc
        if not math.isfinite(t):
            raise DataFormatError(f"{path}:{lineno}: timestamp is NaN or infinite: {parts[0]!r}")
        if stamps and t <= stamps[-1]:
            kind = "duplicate" if t == stamps[-1] else "decreasing"
            raise DataFormatError(
                f"{path}:{lineno}: {kind} timestamp {parts[0]} (line {lines[-1]} has {stamps[-1]!r}); "
                "timestamps must strictly increase"
            )
        stamps.append(t)
        fields.append(parts[1:])
        lines.append(lineno)
    return np.asarray(stamps, dtype=np.float64), fields, lines


def _read_stamped_values(path: Path, columns: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Read ``timestamp v1 v2 ...`` lines of finite numbers (``_read_stamped_list``'s checks too).

    Returns:
        timestamps: (M,) float64 seconds; values: (M, C) float64, C = the columns after the stamp.
    """
    stamps, fields, lines = _read_stamped_list(path, columns)
    values = np.zeros((len(fields), len(columns.split()) - 1), dtype=np.float64)
    for k, (row, lineno) in enumerate(zip(fields, lines)):
        try:
            values[k] = [float(v) for v in row]
        except ValueError as exc:
            raise DataFormatError(f"{path}:{lineno}: not a number ({exc})") from exc
        if not np.isfinite(values[k]).all():
            raise DataFormatError(f"{path}:{lineno}: NaN or infinite {what}")
    return stamps, values


def _read_accelerometer(path: Path) -> tuple[Tensor, Tensor]:
    """Read ``timestamp ax ay az`` lines into (M,) float64 seconds and (M, 3) float64 m/s^2."""
    stamps, values = _read_stamped_values(path, "timestamp ax ay az", "acceleration")
    return torch.from_numpy(stamps), torch.from_numpy(values)


def _read_imu(path: Path) -> ImuData:
    """Read ``imu.txt`` (``timestamp gx gy gz ax ay az``; rad/s, m/s^2, camera frame) into ImuData."""
    stamps, values = _read_stamped_values(path, "timestamp gx gy gz ax ay az", "IMU value")
    if stamps.size == 0:
        raise DataFormatError(f"{path}: no IMU samples (expected lines 'timestamp gx gy gz ax ay az')")
    # Moving or not, an accelerometer's reading is about gravity's magnitude most of the time: a
    # median far from it means other units (g, as many devices log it) or columns out of order.
    median = float(np.median(np.linalg.norm(values[:, 3:], axis=1)))
    if not _IMU_GRAVITY_RANGE[0] <= median <= _IMU_GRAVITY_RANGE[1]:
        hint = " (in g? multiply ax ay az by 9.81)" if 0.5 <= median <= 2.0 else ""
        raise DataFormatError(
            f"{path}: the specific force's median magnitude is {median:.3g}, expected about 9.81 "
            f"(ax ay az in m/s^2, gravity included){hint}"
        )
    values_t = torch.from_numpy(values)
    return ImuData(torch.from_numpy(stamps), values_t[:, :3].contiguous(), values_t[:, 3:].contiguous())


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{name}: expected an integer >= {minimum}, got {value}")
    return int(value)


def _check_seconds(value, name: str, allow_zero: bool) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ConfigError(f"{name}: expected a finite number of seconds {bound}, got {value!r}")
    return v


#: Largest depth-stream latency ``depth_time_offset`` takes, seconds (a few frames of a 30 Hz camera
#: and more; a larger value is a mistake of units, not a latency).
MAX_DEPTH_TIME_OFFSET = 0.5


def check_depth_time_offset(value, name: str) -> float:
    """``value`` as a depth-stream latency in seconds, finite and within ``MAX_DEPTH_TIME_OFFSET``.

    Raises:
        ConfigError: naming ``name`` for anything else.
    """
    try:
        v = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and abs(v) <= MAX_DEPTH_TIME_OFFSET):
        raise ConfigError(f"{name}: expected seconds within +-{MAX_DEPTH_TIME_OFFSET}, got {value!r}")
    return v


def _image_complete(buf: np.ndarray) -> bool:
    """Return False for a PNG or JPEG whose end marker is missing (a truncated file)."""
    head = buf[:8].tobytes()
    tail = buf[-_TAIL_BYTES:].tobytes()
    if head.startswith(_PNG_SIGNATURE):
        return b"IEND" in tail
    if head.startswith(_JPEG_SIGNATURE):
        return b"\xff\xd9" in tail
    return True


def _read_image(path: Path, flags: int, where: str, fast: dict[str, bool] | None = None) -> np.ndarray:
    """Read and decode one image file; raise CorruptImageError naming it if that fails.

    A colour image (``flags`` ``IMREAD_COLOR``) comes back in RGB order, anything else as
    OpenCV's ``imdecode`` gives it. With ``fast`` (the sequence's per-stream switches, keyed
    "colour" and "other"), a simple PNG is decoded by :func:`torchslam.data.png.decode_png`
    (the same pixels, about 3x faster); a stream whose image that path declines (another PNG
    filter, a JPEG) stops trying it, so it costs at most one inflate per stream.
    """
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise CorruptImageError(f"{path} ({where}): cannot read image ({exc.strerror or exc})") from exc
    if buf.size == 0:
        raise CorruptImageError(f"{path} ({where}): empty image file")
    if not _image_complete(buf):
        raise CorruptImageError(f"{path} ({where}): truncated image file (end marker missing)")
    colour = flags == cv2.IMREAD_COLOR
    stream = "colour" if colour else "other"
    if fast is not None and fast.get(stream) and flags in (cv2.IMREAD_COLOR, cv2.IMREAD_UNCHANGED):
        img = decode_png(buf, colour)
        if img is not None:
            return img
        fast[stream] = False
    img = cv2.imdecode(buf, flags)
    if img is None:
        raise CorruptImageError(f"{path} ({where}): cannot decode image (corrupt or not an image)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if colour and img.ndim == 3 else img


class TUMSequence:
    """An RGB-D sequence in TUM layout, decoded lazily frame by frame.

    Implements the ``torchslam.data.Sequence`` protocol.

    Args:
        root: the sequence folder (``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``,
            ``accelerometer.txt``, ``calibration.txt``, ``imu.txt``).
        max_gap: largest |t_rgb - t_depth| for a colour and a depth image to pair, seconds.
        stride: keep every ``stride``-th associated frame.
        start: first associated frame kept (index into the associated pairs).
        end: one past the last associated frame kept, or None for all.
        prefetch: frames decoded ahead by a background thread during iteration (0 = none).
        camera: intrinsics overriding ``calibration.txt`` and the folder-name preset.
        depth_scale: raw depth units per metre overriding ``calibration.txt`` and the preset.
        invalid_depth: raw depth values that mean "no measurement"; they become 0.
        register_colour: resample each colour image onto the depth image's pixels where the
            calibration gives the colour camera's own intrinsics (``calibration.colour_camera``:
            a ``colour`` line of ``calibration.txt`` or the 7-Scenes preset); False keeps the
            colour image as it is.
        pin_memory: decode into page-locked host memory, so that a CUDA system's copy of each
            frame to the GPU runs without staging and without blocking the host (needs CUDA).
        fast_png: decode simple PNGs on ``png.decode_png`` (the same pixels as OpenCV, faster);
            False decodes every image with OpenCV.
        gt_max_gap: largest spacing of the two ground-truth poses bracketing a frame across
            which its pose is interpolated, seconds.
        depth_time_offset: each depth image was taken at its stamp plus this, seconds (the depth
            stream's latency against the colour stream's: ``Frame.depth_timestamp``, the instant
            the systems give the depth's geometry, is ``depth.txt``'s stamp plus it). Colour and
            depth are still associated by their stamps as written. ``torchslam calibrate-time
            --stream depth`` estimates it from the images
            (:func:`~torchslam.app.calibrate_time.estimate_depth_time_offset`).

    Attributes:
        name: the folder name.
        root: the folder.
        camera: pinhole intrinsics and image size.
        depth_scale: raw depth units per metre.
        calibration_source: where ``camera`` and ``depth_scale`` came from.
        colour_camera: the unregistered colour image's intrinsics every colour image is
            registered with, or None (registered already, or ``register_colour=False``).
        colour_source: where ``colour_camera`` came from, or None.
        readout_time: the sensor's rolling-shutter readout, seconds from the first image row to
            the last: ``calibration.txt``'s ``readout`` line, else the folder name's sensor (a
            Kinect v1 for freiburg1/2 and 7-Scenes: 0.03), else 0
            (:func:`~torchslam.data.calibration.readout_for`).
        readout_source: where ``readout_time`` came from, or None where none is known.
        timestamps: (N,) float64 colour timestamps of the frames, seconds.
        depth_timestamps: (N,) float64 instants of the paired depth images, seconds: their stamps
            plus ``depth_time_offset``.
        depth_time_offset: as given.
        rgb_paths, depth_paths: the N image files.
        association: pairing statistics over the whole folder.
        groundtruth: Trajectory of the ground-truth pose at every frame timestamp the ground truth
            covers (a subset of ``timestamps``), or None without ``groundtruth.txt``.
        groundtruth_raw: the ground-truth file as read, or None.
        gt_valid: (N,) bool, which frames have a ground-truth pose.
        gt_bracket_gap: (N,) float64 spacing of the two ground-truth poses bracketing each frame,
            seconds (inf outside the ground-truth span or without ground truth).
        accelerometer: ((M,) float64 seconds, (M, 3) float64 m/s^2) or None.
        imu: the ``imu.txt`` stream (gyro rad/s, specific force m/s^2, camera frame), or None.
        attitude: the AHRS attitude of ``imu`` (source "imu"; see the module docstring), or None.
        skipped: (index, reason) of frames skipped by the latest iteration (corrupt images, or
            images of the wrong size or format after the first frame; see ``__iter__``).

    Raises:
        DataFormatError: naming the file and line for a missing list, a malformed or
            non-increasing list line (``imu.txt`` included), a listed image that does not exist,
            bad ground truth or calibration, or no associated frames.
        ConfigError: naming the argument for a bad ``max_gap``, ``stride``, ``start``, ``end``,
            ``prefetch``, ``invalid_depth``, ``gt_max_gap`` or ``depth_time_offset``.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        max_gap: float = 0.02,
        stride: int = 1,
        start: int = 0,
        end: int | None = None,
        prefetch: int = 0,
        camera: PinholeCamera | None = None,
        depth_scale: float | None = None,
        invalid_depth: Iterable[int] = (0, 65535),
        gt_max_gap: float = 0.2,
        register_colour: bool = True,
        pin_memory: bool = False,
        fast_png: bool = True,
        depth_time_offset: float = 0.0,
    ) -> None:
        root = Path(root)
        self.depth_time_offset = check_depth_time_offset(depth_time_offset, "depth_time_offset")
        max_gap = _check_seconds(max_gap, "max_gap", allow_zero=True)
        gt_max_gap = _check_seconds(gt_max_gap, "gt_max_gap", allow_zero=False)
        stride = _check_int(stride, "stride", 1)
        start = _check_int(start, "start", 0)
        if end is not None:
            end = _check_int(end, "end", 1)
        self.prefetch = _check_int(prefetch, "prefetch", 0)
        if not isinstance(pin_memory, bool):
            raise ConfigError(f"pin_memory: expected True or False, got {pin_memory!r}")
        if not isinstance(fast_png, bool):
            raise ConfigError(f"fast_png: expected True or False, got {fast_png!r}")
        if pin_memory and not torch.cuda.is_available():
            raise ConfigError("pin_memory: page-locked frames are for copies to a CUDA device, and none is available")
        self.pin_memory = pin_memory
        try:
            invalid = tuple(int(v) for v in invalid_depth)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"invalid_depth: expected raw 16-bit values, got {invalid_depth!r}") from exc
        if any(not 0 <= v <= 65535 for v in invalid):
            raise ConfigError(f"invalid_depth: values must lie in [0, 65535], got {invalid}")
        self.invalid_depth = invalid
        # 0 means "no measurement" whatever the list says: it divides to 0 m.
        self._invalid_nonzero = np.asarray([v for v in invalid if v != 0], dtype=np.uint16)

        if not root.is_dir():
            raise DataFormatError(f"{root}: not a folder (expected a TUM RGB-D sequence folder)")
        missing = [n for n in (RGB_LIST, DEPTH_LIST) if not (root / n).is_file()]
        if missing:
            raise DataFormatError(
                f"{root}: not a TUM RGB-D sequence: missing {' and '.join(missing)} "
                f"(expected {RGB_LIST} and {DEPTH_LIST} with lines 'timestamp path')"
            )
        self.root = root
        self.name = root.resolve().name
        calib: Calibration = resolve_calibration(root, camera, depth_scale)
        self.camera = calib.camera
        self.depth_scale = float(calib.depth_scale)
        self.calibration_source = calib.source
        self.readout_time, self.readout_source = calib.readout_time, calib.readout_source
        if not isinstance(register_colour, bool):
            raise ConfigError(f"register_colour: expected true or false, got {register_colour!r}")
        # An unregistered colour image is resampled onto the depth image's pixels at decode.
        use_colour = register_colour and calib.colour_camera is not None
        self.colour_camera = calib.colour_camera if use_colour else None
        self.colour_source = calib.colour_source if use_colour else None
        self._colour_maps = colour_to_depth_maps(self.camera, self.colour_camera) if use_colour else None
        # Per stream: decode PNGs on the fast path (``_read_image``) until one is declined.
        fast = fast_png and png_available()
        self._fast_decode = {"colour": fast, "other": fast}

        rgb_list, depth_list = root / RGB_LIST, root / DEPTH_LIST
        rgb_t, rgb_f, rgb_lines = _read_stamped_list(rgb_list, "timestamp filename")
        depth_t, depth_f, depth_lines = _read_stamped_list(depth_list, "timestamp filename")
        rgb_paths = [root / f[0] for f in rgb_f]
        depth_paths = [root / f[0] for f in depth_f]
        for list_path, paths, lines in ((rgb_list, rgb_paths, rgb_lines), (depth_list, depth_paths, depth_lines)):
            absent = [(p, ln) for p, ln in zip(paths, lines) if not p.is_file()]
            if absent:
                more = f" (and {len(absent) - 1} more missing)" if len(absent) > 1 else ""
                raise DataFormatError(f"{list_path}:{absent[0][1]}: listed image {absent[0][0]} does not exist{more}")

        idx_r, idx_d = associate_timestamps(torch.from_numpy(rgb_t), torch.from_numpy(depth_t), max_gap)
        idx_r, idx_d = idx_r.numpy(), idx_d.numpy()
        n_pairs = int(idx_r.size)
        if n_pairs == 0:
            detail = "one of the lists is empty" if rgb_t.size == 0 or depth_t.size == 0 else (
                f"the closest colour-depth stamps are {_closest_gap(rgb_t, depth_t):.6f} s apart"
            )
            raise DataFormatError(
                f"{root}: empty sequence: no {RGB_LIST} entry has a {DEPTH_LIST} entry within max_gap={max_gap} s "
                f"({rgb_t.size} colour, {depth_t.size} depth entries; {detail})"
            )
        gaps = np.abs(rgb_t[idx_r] - depth_t[idx_d])
        self.association = AssociationStats(
            rgb_count=int(rgb_t.size),
            depth_count=int(depth_t.size),
            pairs=n_pairs,
            dropped_rgb=int(rgb_t.size - n_pairs),
            dropped_depth=int(depth_t.size - n_pairs),
            max_gap_s=float(gaps.max()),
            mean_gap_s=float(gaps.mean()),
            max_gap_allowed_s=max_gap,
            mean_depth_minus_colour_s=float((depth_t[idx_d] - rgb_t[idx_r]).mean()),
        )

        if start >= n_pairs:
            raise ConfigError(f"start: {start} is past the last of the {n_pairs} associated frames of {root}")
        if end is not None and end > n_pairs:
            raise ConfigError(f"end: {end} is past the {n_pairs} associated frames of {root}")
        if end is not None and end <= start:
            raise ConfigError(f"end: {end} must be greater than start ({start})")
        sel = np.arange(start, n_pairs if end is None else end, stride)
        idx_r, idx_d = idx_r[sel], idx_d[sel]
        self.timestamps = torch.from_numpy(rgb_t[idx_r].copy())
        self.depth_timestamps = torch.from_numpy(depth_t[idx_d] + self.depth_time_offset)
        self.rgb_paths = [rgb_paths[i] for i in idx_r]
        self.depth_paths = [depth_paths[i] for i in idx_d]
        self._rgb_where = [f"{rgb_list.name}:{rgb_lines[i]}" for i in idx_r]
        self._depth_where = [f"{depth_list.name}:{depth_lines[i]}" for i in idx_d]
        n = int(sel.size)

        self.gt_max_gap = gt_max_gap
        self.groundtruth_raw: Trajectory | None = None
        self.groundtruth: Trajectory | None = None
        self.gt_valid = torch.zeros(n, dtype=torch.bool)
        self.gt_bracket_gap = torch.full((n,), math.inf, dtype=torch.float64)
        self._T_wc = torch.eye(4, dtype=torch.float64).expand(n, 4, 4).clone()
        if (root / GROUNDTRUTH_FILE).is_file():
            gt = read_tum_trajectory(root / GROUNDTRUTH_FILE)
            self.groundtruth_raw = gt
            self._T_wc, self.gt_valid = gt.interpolate(self.timestamps, max_gap=gt_max_gap)
            self.gt_bracket_gap = _bracket_gap(gt.timestamps, self.timestamps)
            self.groundtruth = Trajectory(self.timestamps[self.gt_valid], self._T_wc[self.gt_valid])
            if not bool(self.gt_valid.any()):
                logger.warning("%s: %s covers none of the %d frames", root, GROUNDTRUTH_FILE, n)

        self.accelerometer: tuple[Tensor, Tensor] | None = None
        if (root / ACCELEROMETER_FILE).is_file():
            self.accelerometer = _read_accelerometer(root / ACCELEROMETER_FILE)
        self.imu: ImuData | None = None
        self.attitude: AttitudeStream | None = None
        if (root / IMU_FILE).is_file():
            self.imu = _read_imu(root / IMU_FILE)
            self.attitude = ahrs_attitude(self.imu, self._imu_start_attitude(root / IMU_FILE))
        self.skipped: list[tuple[int, str]] = []

    def _imu_start_attitude(self, path: Path) -> Tensor | None:
        """The ground-truth rotation at the first IMU sample where it may start the filter, else None.

        The filter needs a z-up world: a ground truth whose world up differs from the up that the
        stream's first seconds of specific force show (``imu.start_up``) by more than
        ``_IMU_START_MAX_TILT_DEG`` is not used (with a warning), and the filter starts levelled
        by gravity instead.
        """
        imu, gt = self.imu, self.groundtruth_raw
        if imu is None or gt is None:
            return None
        T0, ok = gt.interpolate(imu.timestamps[:1], max_gap=self.gt_max_gap)
        if not bool(ok[0]):
            return None
        R0 = T0[0, :3, :3]
        up_w = R0 @ start_up(imu)
        cos_tilt = float(up_w[2])
        tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt))))
        if tilt_deg > _IMU_START_MAX_TILT_DEG:
            logger.warning(
                "%s: the ground truth's world is not z-up (the measured up is %.0f deg off its +z at the start of the IMU "
                "stream); the attitude filter starts levelled by gravity with zero yaw instead", path, tilt_deg,
            )
            return None
        return R0

    @property
    def fast_png_streams(self) -> dict[str, bool]:
        """Whether the colour and the other (depth) images still decode on the PNG fast path
        (``fast_png``): a stream leaves it at the first image the path declines."""
        return dict(self._fast_decode)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    def __repr__(self) -> str:
        return (
            f"TUMSequence({str(self.root)!r}, frames={len(self)}, camera={self.camera}, "
            f"depth_scale={self.depth_scale}, calibration={self.calibration_source!r})"
        )

    def __getitem__(self, index: int) -> Frame:
        """Decode frame ``index`` (negative indices count from the end).

        Raises:
            IndexError: for an index out of range.
            CorruptImageError: (a DataFormatError) naming the file of an undecodable image.
            ImageFormatError: (a DataFormatError) naming the file of an image with the wrong size
                or pixel format.
        """
        n = len(self)
        i = operator.index(index)
        if not -n <= i < n:
            raise IndexError(f"index: {index} out of range for a sequence of {n} frames")
        return self._load(i % n)

    def __iter__(self) -> Iterator[Frame]:
        """Yield the frames in order, skipping (with a warning) those whose images are unusable.

        A frame is skipped, and recorded in ``skipped`` with the reason, when an image is corrupt
        (truncated, undecodable) or, once a frame of the iteration has decoded, when an image has
        the wrong size or pixel format (an 8-bit depth map, a resized colour image): one odd frame
        in a sequence must not lose the frames tracked before it. A size or format error before
        any frame has decoded means the folder disagrees with its calibration and is raised.

        With ``prefetch > 0`` a background thread decodes up to ``prefetch`` frames ahead; OpenCV
        and NumPy release the GIL while decoding and converting, so this overlaps the consumer's
        work (fully where the consumer's work releases the GIL too, as torch kernels do).
        ``skipped`` is reset at the start of each iteration; the iterator must not be shared by
        two concurrent iterations of the same sequence.
        """
        self.skipped = []
        if self.prefetch == 0:
            return self._iter_plain()
        return self._iter_prefetch(self.prefetch)

    def _iter_plain(self) -> Iterator[Frame]:
        decoded = False
        for i in range(len(self)):
            try:
                frame = self._load(i)
            except (CorruptImageError, ImageFormatError) as exc:
                if not _skippable(exc, decoded):
                    raise
                self._skip(i, exc)
                continue
            decoded = True
            yield frame

    def _iter_prefetch(self, ahead: int) -> Iterator[Frame]:
        slots = threading.Semaphore(ahead)
        results: queue.SimpleQueue = queue.SimpleQueue()
        stop = threading.Event()
        done = object()

        def work() -> None:
            name_os_thread("tslam-decode")
            try:
                for i in range(len(self)):
                    while not slots.acquire(timeout=0.05):
                        if stop.is_set():
                            return
                    if stop.is_set():
                        return
                    try:
                        results.put((i, self._load(i), None))
                    except (CorruptImageError, ImageFormatError) as exc:
                        results.put((i, None, exc))
            except BaseException as exc:  # handed to the consumer, which re-raises it
                results.put((-1, None, exc))
                return
            results.put(done)

        worker = threading.Thread(target=work, name=f"torchslam-prefetch-{self.name}", daemon=True)
        worker.start()
        decoded = False
        try:
            while True:
                item = results.get()
                if item is done:
                    return
                i, frame, exc = item
                slots.release()
                if frame is None:
                    if _skippable(exc, decoded):
                        self._skip(i, exc)
                        continue
                    raise exc
                decoded = True
                yield frame
        finally:
            stop.set()
            worker.join()

    def _skip(self, index: int, exc: Exception) -> None:
        logger.warning("%s: skipping frame %d: %s", self.name, index, exc)
        self.skipped.append((index, str(exc)))

    def _load(self, i: int) -> Frame:
        cam = self.camera
        rgb8 = _read_image(self.rgb_paths[i], cv2.IMREAD_COLOR, self._rgb_where[i], self._fast_decode)
        if rgb8.shape[:2] != (cam.height, cam.width):
            raise ImageFormatError(
                f"{self.rgb_paths[i]} ({self._rgb_where[i]}): colour image is {rgb8.shape[1]}x{rgb8.shape[0]}, "
                f"the calibration ({self.calibration_source}) says {cam.width}x{cam.height}"
            )
        if self._colour_maps is not None:
            rgb8 = cv2.remap(rgb8, *self._colour_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        raw = _read_image(self.depth_paths[i], cv2.IMREAD_UNCHANGED, self._depth_where[i], self._fast_decode)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            channels = 1 if raw.ndim == 2 else raw.shape[2]
            raise ImageFormatError(
                f"{self.depth_paths[i]} ({self._depth_where[i]}): depth must be a single-channel 16-bit image, "
                f"got {raw.dtype} with {channels} channel(s)"
            )
        if raw.shape != (cam.height, cam.width):
            raise ImageFormatError(
                f"{self.depth_paths[i]} ({self._depth_where[i]}): depth image is {raw.shape[1]}x{raw.shape[0]}, "
                f"the calibration ({self.calibration_source}) says {cam.width}x{cam.height}"
            )
        # Converted with NumPy/OpenCV, which release the GIL and do not wake torch's intra-op
        # thread pool (beside a busy process, that pool's busy-waiting stalls this step).
        rgb_np = np.empty((3, cam.height, cam.width), dtype=np.float32)  # (3, H, W) RGB in [0, 1]
        for channel, plane in zip(rgb_np, cv2.split(rgb8)):
            np.divide(plane, np.float32(255.0), out=channel, dtype=np.float32)
        metres = raw.astype(np.float32)
        metres /= np.float32(self.depth_scale)
        for value in self._invalid_nonzero:
            metres[raw == value] = 0.0
        T_wc = self._T_wc[i].clone() if bool(self.gt_valid[i]) else None
        rgb, depth = torch.from_numpy(rgb_np), torch.from_numpy(metres)[None]  # (3, H, W), (1, H, W)
        if self.pin_memory:
            rgb, depth = rgb.pin_memory(), depth.pin_memory()
        return Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=rgb,
            depth=depth,
            T_wc=T_wc,
            depth_timestamp=float(self.depth_timestamps[i]),
        )


def _skippable(exc: BaseException, decoded: bool) -> bool:
    """Whether iteration skips a frame that raised ``exc`` (``decoded``: an earlier frame decoded)."""
    return isinstance(exc, CorruptImageError) or (decoded and isinstance(exc, ImageFormatError))


def _closest_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Smallest |a_i - b_j| over sorted stamp arrays, seconds."""
    k = np.clip(np.searchsorted(b, a), 1, max(b.size - 1, 1))
    return float(np.minimum(np.abs(a - b[k - 1]), np.abs(a - b[np.minimum(k, b.size - 1)])).min())


def _bracket_gap(gt_times: Tensor, times: Tensor) -> Tensor:
    """(M,) spacing of the ground-truth stamps bracketing each time (inf outside their span)."""
    n = gt_times.shape[0]
    out = torch.full(times.shape, math.inf, dtype=torch.float64)
    if n == 0:
        return out
    if n == 1:
        return torch.where(times == gt_times[0], torch.zeros_like(out), out)
    hi = torch.searchsorted(gt_times, times).clamp(1, n - 1)
    span = gt_times[hi] - gt_times[hi - 1]
    inside = (times >= gt_times[0]) & (times <= gt_times[-1])
    return torch.where(inside, span, out)


def sequence_info(root: str | os.PathLike, **kwargs) -> dict:
    """Summarise a TUM-layout sequence folder without decoding images.

    Args:
        root: the sequence folder.
        **kwargs: passed to ``TUMSequence`` (``max_gap``, ``stride``, ``camera`` ...).

    Returns:
        A JSON-serialisable dict: ``name``, ``path``, ``frames``, ``first_timestamp_s``,
        ``duration_s``; ``rgb_list_count``, ``depth_list_count``, ``associated_count``,
        ``dropped_rgb``, ``dropped_depth``, ``association_max_gap_s``, ``association_mean_gap_s``,
        ``association_max_gap_allowed_s``, ``association_mean_depth_minus_colour_s``;
        ``intrinsics`` (fx, fy, cx, cy in pixels), ``intrinsics_source``, ``depth_scale``,
        ``readout_time_s`` and ``readout_source`` (the sensor's rolling-shutter readout,
        ``TUMSequence.readout_time``), ``image_size`` (width, height); ``gt_poses`` (poses in groundtruth.txt, 0 without it),
        ``gt_frames_covered``, ``gt_coverage_fraction``, ``gt_frames_interpolated_across_gap``
        (covered frames whose bracketing poses are more than 1.5 times the median ground-truth
        spacing apart), ``gt_largest_gap_s``,
        ``gt_max_gap_allowed_s``; ``colour_registered_with`` (the colour camera the colour images
        are registered with and its source, or None); ``accelerometer_samples`` (0 without accelerometer.txt);
        ``imu_samples`` (0 without imu.txt).

    Raises:
        DataFormatError / ConfigError: as ``TUMSequence``.
    """
    seq = TUMSequence(root, **kwargs)
    cam = seq.camera
    t = seq.timestamps
    assoc = asdict(seq.association)
    info = {
        "name": seq.name,
        "path": str(seq.root.resolve()),
        "frames": len(seq),
        "first_timestamp_s": float(t[0]),
        "duration_s": float(t[-1] - t[0]),
        "rgb_list_count": assoc["rgb_count"],
        "depth_list_count": assoc["depth_count"],
        "associated_count": assoc["pairs"],
        "dropped_rgb": assoc["dropped_rgb"],
        "dropped_depth": assoc["dropped_depth"],
        "association_max_gap_s": assoc["max_gap_s"],
        "association_mean_gap_s": assoc["mean_gap_s"],
        "association_max_gap_allowed_s": assoc["max_gap_allowed_s"],
        "association_mean_depth_minus_colour_s": assoc["mean_depth_minus_colour_s"],
        "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy},
        "intrinsics_source": seq.calibration_source,
        "colour_registered_with": None if seq.colour_camera is None else {
            "fx": seq.colour_camera.fx, "fy": seq.colour_camera.fy, "cx": seq.colour_camera.cx, "cy": seq.colour_camera.cy,
            "source": seq.colour_source,
        },
        "depth_scale": seq.depth_scale,
        "readout_time_s": seq.readout_time,
        "readout_source": seq.readout_source,
        "image_size": {"width": cam.width, "height": cam.height},
        "gt_poses": 0,
        "gt_frames_covered": 0,
        "gt_coverage_fraction": 0.0,
        "gt_frames_interpolated_across_gap": 0,
        "gt_largest_gap_s": None,
        "gt_max_gap_allowed_s": seq.gt_max_gap,
        "accelerometer_samples": 0 if seq.accelerometer is None else int(seq.accelerometer[0].shape[0]),
        "imu_samples": 0 if seq.imu is None else len(seq.imu),
    }
    gt = seq.groundtruth_raw
    if gt is not None:
        covered = int(seq.gt_valid.sum())
        info["gt_poses"] = len(gt)
        info["gt_frames_covered"] = covered
        info["gt_coverage_fraction"] = covered / len(seq)
        if len(gt) >= 2:
            spacing = gt.timestamps[1:] - gt.timestamps[:-1]
            info["gt_largest_gap_s"] = float(spacing.max())
            across = seq.gt_valid & (seq.gt_bracket_gap > 1.5 * float(spacing.median()))
            info["gt_frames_interpolated_across_gap"] = int(across.sum())
    return info
