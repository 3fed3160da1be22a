"""Camera calibration of RGB-D sequences: TUM/ICL-NUIM presets and per-folder ``calibration.txt``.

Convention:
    Intrinsics are pixels with pixel centres at integer coordinates (``u = fx x / z + cx``), as
    everywhere in torchslam. ``depth_scale`` converts raw 16-bit depth to metres:
    ``metres = raw / depth_scale`` (5000 for TUM RGB-D and ICL-NUIM, 1000 for millimetre sensors).

A ``calibration.txt`` holds, after any ``#`` comment lines, exactly one line
``fx fy cx cy depth_scale width height``, optionally followed by 4, 5 or 8 lens distortion
coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (``PinholeCamera.distortion``). Those are the
intrinsics of the depth image. Where the colour image is not registered to it, an optional
second line ``colour fx fy cx cy`` gives the colour camera's own intrinsics (same centre,
orientation and image size as the depth camera, no distortion); the loader then registers every
colour image to the depth image (``colour_to_depth_maps``).

Colour presets (``COLOUR_PRESETS``): 7-Scenes colour and depth come from the Kinect unregistered,
and the dataset publishes only the depth intrinsics (585, 585, 320, 240). For a folder whose name
says 7-Scenes (``7scenes``, ``7-scenes``, ``7_scenes``) and whose depth intrinsics are exactly
those, with no ``colour`` line, torchslam uses the colour intrinsics of an independent calibration
of the 7-Scenes Kinect (fx 532.57, fy 531.54, cx 320, cy 240). The few centimetres between the
two cameras' centres are left out: their direction is not documented, and either sign changed
NI-SLAM's ATE on frames 0-299 of redkitchen by under 0.3 cm, against 7.3 -> 3.0 cm for the
intrinsics alone.

Rolling shutter (``readout_for``): a ``calibration.txt`` may hold a line ``readout SECONDS``, the
time its sensor takes to read its image rows from the first to the last (0: a global shutter,
at most ``MAX_READOUT_S``). Without one, a folder named for a dataset recorded with a Kinect v1
(``freiburg1``/``fr1``, ``freiburg2``/``fr2``, 7-Scenes) gets ``READOUT_PRESETS``' 0.03 s: a
Kinect v1 reads the rows of both its cameras one after another over most of its 33 ms frame
period. Any other folder has no known readout (0): freiburg3's camera, ICL-NUIM's renderer, and
every sensor torchslam has no record of. GC-SLAM's dense front-end models it
(``GCSlamConfig.readout_time``).

Plausibility (``intrinsics_problem``), checked wherever intrinsics enter torchslam (a
``calibration.txt``, an explicit camera, the presets, the synthetic generator's settings):

- the principal point lies inside the image, ``-0.5 <= cx <= width - 0.5`` and likewise ``cy``
  (pixel centres at integers, so the image edges are at -0.5 and ``width - 0.5``);
- the field of view ``2 atan(width / (2 fx))`` (and ``2 atan(height / (2 fy))``) lies between
  ``MIN_FOV_DEG`` = 10 and ``MAX_FOV_DEG`` = 170 degrees: for a 640-pixel-wide image
  ``28 <= fx <= 3658`` (TUM's Kinects: about 58 degrees, fx = 517-535);
- ``DEPTH_SCALE_RANGE``: ``1 <= depth_scale <= 100000`` raw units per metre (1: raw values in
  metres, 1000: millimetres, 5000: TUM, 100000: 10 micrometre steps).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataFormatError, ShapeError
from ..geometry import PinholeCamera

__all__ = [
    "COLOUR_PRESETS", "CameraPreset", "Calibration", "DEPTH_SCALE_RANGE", "INTRINSICS_PRESETS", "MAX_FOV_DEG",
    "MIN_FOV_DEG", "colour_preset_for", "colour_to_depth_maps", "intrinsics_problem", "preset_for_name",
    "MAX_READOUT_S", "READOUT_PRESETS", "read_calibration", "read_colour_camera", "read_readout", "readout_for",
    "readout_preset_for", "resolve_calibration",
]

CALIBRATION_FILE = "calibration.txt"

# Plausible intrinsics (module docstring): field of view per axis, degrees, and raw depth units per metre.
MIN_FOV_DEG = 10.0
MAX_FOV_DEG = 170.0
DEPTH_SCALE_RANGE = (1.0, 100000.0)


def focal_range(size: int) -> tuple[float, float]:
    """Smallest and largest focal length, pixels, of an image axis of ``size`` pixels whose field of
    view lies in ``[MIN_FOV_DEG, MAX_FOV_DEG]``: ``size / (2 tan(fov / 2))``."""
    return (size / (2.0 * math.tan(math.radians(MAX_FOV_DEG) / 2)), size / (2.0 * math.tan(math.radians(MIN_FOV_DEG) / 2)))


def intrinsics_problem(
    fx: float, fy: float, cx: float, cy: float, width: int, height: int, depth_scale: float | None = None
) -> tuple[str, str] | None:
    """Say what is implausible about pinhole intrinsics (module docstring for the limits), or None.

    Args:
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels (pixel centres at integers).
        width, height: image size, pixels.
        depth_scale: raw depth units per metre, or None to skip that check.

    Returns:
        None when plausible, else ``(field, reason)``: the first offending value's name
        (``"fx"``, ``"cx"``, ``"depth_scale"`` ...) and what was expected and received.
    """
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, **({} if depth_scale is None else {"depth_scale": depth_scale})}
    for name, v in values.items():
        if not math.isfinite(v):
            return name, f"expected a finite number, got {v!r}"
    for name, f, size, axis in (("fx", fx, width, "horizontal"), ("fy", fy, height, "vertical")):
        low, high = focal_range(size)
        if not low <= f <= high:
            fov = math.degrees(2 * math.atan(size / (2 * f))) if f > 0 else float("nan")
            return name, (
                f"{name} = {f:g} px gives a {axis} field of view of {fov:.3g} degrees over {size} px; a camera has "
                f"{MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} degrees, i.e. {low:.4g} <= {name} <= {high:.4g} px"
            )
    for name, c, size in (("cx", cx, width), ("cy", cy, height)):
        if not -0.5 <= c <= size - 0.5:
            return name, f"principal point {name} = {c:g} px lies outside the image (-0.5 to {size - 0.5:g} px for {size} px)"
    if depth_scale is not None and _depth_scale_problem(depth_scale) is not None:
        return "depth_scale", _depth_scale_problem(depth_scale)
    return None


def _depth_scale_problem(depth_scale: float) -> str | None:
    if DEPTH_SCALE_RANGE[0] <= depth_scale <= DEPTH_SCALE_RANGE[1]:
        return None
    low, high = DEPTH_SCALE_RANGE
    return f"depth_scale: expected {low:g} to {high:g} raw depth units per metre (1000: millimetres, 5000: TUM), got {depth_scale:g}"


def _camera_problem(camera: PinholeCamera, depth_scale: float | None = None) -> tuple[str, str] | None:
    c = camera
    return intrinsics_problem(c.fx, c.fy, c.cx, c.cy, c.width, c.height, depth_scale)


@dataclass(frozen=True)
class CameraPreset:
    """Published intrinsics of a camera: pinhole model and raw-depth-to-metres divisor."""

    camera: PinholeCamera
    depth_scale: float


@dataclass(frozen=True)
class Calibration:
    """The calibration a sequence uses and where it came from.

    Attributes:
        camera: pinhole intrinsics and image size.
        depth_scale: raw depth units per metre.
        source: ``"preset:<name>"``, ``"calibration.txt"``, ``"argument"`` or a mix such as
            ``"argument (camera), calibration.txt (depth_scale)"``.
        colour_camera: intrinsics of an unregistered colour image (module docstring), or None
            where colour is registered to depth.
        colour_source: where ``colour_camera`` came from (``"calibration.txt"``,
            ``"preset:7scenes"``), or None.
        readout_time: the sensor's rolling-shutter readout, seconds from its first image row to
            its last (module docstring); 0 where none is known.
        readout_source: where ``readout_time`` came from (``"calibration.txt"``,
            ``"preset:freiburg1"``, ``"preset:7scenes"`` ...), or None where none is known.
    """

    camera: PinholeCamera
    depth_scale: float
    source: str
    colour_camera: PinholeCamera | None = None
    colour_source: str | None = None
    readout_time: float = 0.0
    readout_source: str | None = None


# Published TUM RGB-D lens distortion (k1 k2 p1 p2 k3) of the freiburg1 and freiburg2 Kinects,
# whose images are distributed without undistortion; freiburg3 images are already undistorted.
FREIBURG1_DISTORTION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
FREIBURG2_DISTORTION = (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)

# TUM RGB-D "ROS default" intrinsics per Kinect (freiburg1/2/3) and ICL-NUIM, all 640x480 with
# depth scale 5000. ICL-NUIM publishes fy = -480.0 because its renderer's image y axis points up;
# the TUM-format ICL-NUIM release stores images with y down, so torchslam uses fy = +480.0.
INTRINSICS_PRESETS: dict[str, CameraPreset] = {
    "freiburg1": CameraPreset(PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480, FREIBURG1_DISTORTION), 5000.0),
    "freiburg2": CameraPreset(PinholeCamera(520.9, 521.0, 325.1, 249.7, 640, 480, FREIBURG2_DISTORTION), 5000.0),
    "freiburg3": CameraPreset(PinholeCamera(535.4, 539.2, 320.1, 247.6, 640, 480), 5000.0),
    "icl_nuim": CameraPreset(PinholeCamera(481.20, 480.00, 319.50, 239.50, 640, 480), 5000.0),
}

# A preset name inside a folder name: "freiburg1"/"fr1" (not "fr12"), or "icl" as a word start.
_PRESET_PATTERNS = [
    (re.compile(r"(?<![a-z0-9])(?:freiburg|fr)_?([123])(?![0-9])"), lambda m: f"freiburg{m.group(1)}"),
    (re.compile(r"(?<![a-z])icl(?![a-z])"), lambda m: "icl_nuim"),
]


def preset_for_name(name: str) -> str | None:
    """Return the preset key a sequence folder name implies, or None.

    ``rgbd_dataset_freiburg1_xyz`` and ``tum_fr1_xyz`` give ``"freiburg1"``; ``icl_living_room``
    gives ``"icl_nuim"``.
    """
    low = name.lower()
    for pattern, key in _PRESET_PATTERNS:
        match = pattern.search(low)
        if match:
            return key(match)
    return None


def read_calibration(path: str | os.PathLike) -> tuple[PinholeCamera, float]:
    """Read a ``calibration.txt``: one line ``fx fy cx cy depth_scale width height [k1 k2 p1 p2 [k3 [k4 k5 k6]]]``.

    Blank lines and lines starting with ``#`` are skipped.

    Args:
        path: the calibration file.

    Returns:
        camera: pinhole intrinsics (pixels) and image size.
        depth_scale: raw depth units per metre.

    Raises:
        DataFormatError: naming the file (and line) for an unreadable file, a missing or repeated
            data line, a wrong number of values, a non-number, a non-positive value, or
            implausible intrinsics (``intrinsics_problem``).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: cannot read calibration ({exc})") from exc
    found: tuple[int, list[str]] | None = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#") or s.split()[0] in (COLOUR_KEYWORD, READOUT_KEYWORD):
            continue
        if found is not None:
            raise DataFormatError(
                f"{path}:{lineno}: a second calibration line (line {found[0]} already gives one); "
                "expected exactly one line 'fx fy cx cy depth_scale width height'"
            )
        found = (lineno, s.split())
    if found is None:
        raise DataFormatError(f"{path}: no calibration line; expected one line 'fx fy cx cy depth_scale width height'")
    lineno, parts = found
    where = f"{path}:{lineno}"
    if len(parts) not in (7, 11, 12, 15):
        raise DataFormatError(
            f"{where}: expected 7 values 'fx fy cx cy depth_scale width height', optionally followed by 4, 5 "
            f"or 8 distortion coefficients 'k1 k2 p1 p2 [k3 [k4 k5 k6]]', got {len(parts)}"
        )
    try:
        fx, fy, cx, cy, depth_scale = (float(v) for v in parts[:5])
        distortion = tuple(float(v) for v in parts[7:]) or None
    except ValueError as exc:
        raise DataFormatError(f"{where}: not a number ({exc})") from exc
    try:
        width, height = (int(v) for v in parts[5:7])
    except ValueError as exc:
        raise DataFormatError(f"{where}: width and height must be integers, got {parts[5]!r} {parts[6]!r}") from exc
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy, depth_scale, *(distortion or ()))):
        raise DataFormatError(f"{where}: NaN or infinite value")
    if depth_scale <= 0:
        raise DataFormatError(f"{where}: depth_scale must be > 0, got {depth_scale}")
    try:
        camera = PinholeCamera(fx, fy, cx, cy, width, height, distortion)
    except (ShapeError, ConfigError) as exc:
        raise DataFormatError(f"{where}: {exc}") from exc
    problem = _camera_problem(camera, depth_scale)
    if problem is not None:
        raise DataFormatError(f"{where}: implausible calibration: {problem[1]}")
    return camera, depth_scale


COLOUR_KEYWORD = "colour"
READOUT_KEYWORD = "readout"

# Longest rolling-shutter readout accepted, seconds: a frame's rows cannot take longer than a
# 10 Hz frame period.
MAX_READOUT_S = 0.1

# Readout of the sensors the folder-name presets recognise (module docstring): preset -> seconds.
READOUT_PRESETS: dict[str, float] = {"freiburg1": 0.03, "freiburg2": 0.03, "7scenes": 0.03}


def read_readout(path: str | os.PathLike) -> float | None:
    """The readout of a ``calibration.txt``'s ``readout SECONDS`` line, or None without one.

    Raises:
        DataFormatError: naming the file and line for a repeated ``readout`` line, a wrong number
            of values, a non-number, or a value outside ``[0, MAX_READOUT_S]``.
    """
    found = _keyword_line(path, READOUT_KEYWORD, "SECONDS")
    if found is None:
        return None
    where, (value,) = found
    if not 0.0 <= value <= MAX_READOUT_S:  # False for NaN
        raise DataFormatError(
            f"{where}: readout: expected seconds from the first image row to the last in [0, {MAX_READOUT_S:g}] "
            f"(0: a global shutter, 0.03: a Kinect v1), got {value:g}"
        )
    return value


def readout_preset_for(name: str) -> str | None:
    """The ``READOUT_PRESETS`` key a sequence folder ``name`` implies, or None (module docstring)."""
    key = preset_for_name(name)
    if key in READOUT_PRESETS:
        return key
    return "7scenes" if _SEVEN_SCENES.search(name.lower()) else None


def readout_for(root: str | os.PathLike) -> tuple[float, str | None]:
    """``(seconds, source)`` of a sequence folder's rolling-shutter readout (module docstring):
    its ``calibration.txt``'s ``readout`` line, else its folder name's preset, else ``(0.0, None)``.

    Raises:
        DataFormatError: for a malformed ``readout`` line (``read_readout``).
    """
    root = Path(root)
    calib_path = root / CALIBRATION_FILE
    if calib_path.is_file():
        value = read_readout(calib_path)
        if value is not None:
            return value, CALIBRATION_FILE
    key = readout_preset_for(root.resolve().name)
    return (READOUT_PRESETS[key], f"preset:{key}") if key is not None else (0.0, None)


def read_colour_camera(path: str | os.PathLike, camera: PinholeCamera) -> PinholeCamera | None:
    """The colour camera of a ``calibration.txt``'s ``colour fx fy cx cy`` line, or None without one.

    Args:
        path: the calibration file.
        camera: its depth camera (the colour image has the same size).

    Raises:
        DataFormatError: naming the file and line for a repeated ``colour`` line, a wrong number
            of values, a non-number or implausible intrinsics.
    """
    found = _keyword_line(path, COLOUR_KEYWORD, "fx fy cx cy")
    if found is None:
        return None
    where, (fx, fy, cx, cy) = found
    problem = intrinsics_problem(fx, fy, cx, cy, camera.width, camera.height)
    if problem is not None:
        raise DataFormatError(f"{where}: implausible colour intrinsics: {problem[1]}")
    return PinholeCamera(fx, fy, cx, cy, camera.width, camera.height)


def _keyword_line(path: str | os.PathLike, keyword: str, names: str) -> tuple[str, list[float]] | None:
    """``(file:line, values)`` of a ``calibration.txt``'s one ``keyword`` line of the values ``names``
    (space-separated), or None without one; a repeated line, a wrong count or a non-number is a
    DataFormatError naming the file and line."""
    path = Path(path)
    n = len(names.split())
    found = None
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0] != keyword:
            continue
        where = f"{path}:{lineno}"
        if found is not None:
            raise DataFormatError(f"{where}: a second '{keyword}' line (line {found[0]} already gives one)")
        if len(parts) != n + 1:
            raise DataFormatError(f"{where}: expected '{keyword} {names}' ({n} value{'s' if n > 1 else ''}), got {len(parts) - 1} values")
        try:
            found = (lineno, where, [float(v) for v in parts[1:]])
        except ValueError as exc:
            raise DataFormatError(f"{where}: not a number ({exc})") from exc
    return None if found is None else found[1:]


# Colour intrinsics of sensors whose datasets publish only the depth camera's (module docstring):
# preset name -> (the published depth intrinsics it applies to, the colour camera).
COLOUR_PRESETS: dict[str, tuple[tuple[float, float, float, float, int, int], tuple[float, float, float, float]]] = {
    "7scenes": ((585.0, 585.0, 320.0, 240.0, 640, 480), (532.57, 531.54, 320.0, 240.0)),
}
_SEVEN_SCENES = re.compile(r"(?<![a-z0-9])7[-_]?scenes")


def colour_preset_for(name: str, camera: PinholeCamera) -> tuple[str, PinholeCamera] | None:
    """``(preset name, colour camera)`` for a folder ``name`` with depth ``camera``, or None (module docstring)."""
    if not _SEVEN_SCENES.search(name.lower()):
        return None
    depth, (fx, fy, cx, cy) = COLOUR_PRESETS["7scenes"]
    c = camera
    if (c.fx, c.fy, c.cx, c.cy, c.width, c.height) != depth or c.distortion:
        return None
    return "7scenes", PinholeCamera(fx, fy, cx, cy, c.width, c.height)


def colour_to_depth_maps(depth_camera: PinholeCamera, colour_camera: PinholeCamera):
    """``cv2.remap`` maps that register a colour image to the depth image: (H, W) float32 x and y.

    Pixel ``(u, v)`` of the depth image looks along the ray ``((u - cx) / fx, (v - cy) / fy, 1)``
    of the depth camera; the colour camera (same centre and orientation) sees that ray at
    ``(fx_c x + cx_c, fy_c y + cy_c)``.
    """
    d, c = depth_camera, colour_camera
    u = np.arange(d.width, dtype=np.float64)
    v = np.arange(d.height, dtype=np.float64)
    map_x = (c.fx * (u - d.cx) / d.fx + c.cx).astype(np.float32)
    map_y = (c.fy * (v - d.cy) / d.fy + c.cy).astype(np.float32)
    return np.broadcast_to(map_x[None, :], (d.height, d.width)).copy(), np.broadcast_to(map_y[:, None], (d.height, d.width)).copy()


def resolve_calibration(
    root: str | os.PathLike,
    camera: PinholeCamera | None = None,
    depth_scale: float | None = None,
) -> Calibration:
    """Choose a sequence folder's calibration.

    Each of the camera and the depth scale comes from, in order of precedence: the explicit
    argument, the folder's ``calibration.txt``, the preset its folder name implies
    (``freiburg1``/``fr1`` ... ``freiburg3``/``fr3``, ``icl``).

    Args:
        root: the sequence folder.
        camera: explicit intrinsics, or None.
        depth_scale: explicit raw depth units per metre, or None.

    Returns:
        The chosen calibration and its source, with the sensor's rolling-shutter readout
        (:func:`readout_for`: the file's ``readout`` line, else the folder name's sensor, else 0).

    Raises:
        DataFormatError: when neither argument, file nor preset gives a value (the message says
            to add ``calibration.txt``), or ``calibration.txt`` is malformed.
        ShapeError: for a ``camera`` that is not a PinholeCamera.
        ConfigError: for implausible ``camera`` intrinsics, or a ``depth_scale`` outside
            ``DEPTH_SCALE_RANGE``.
    """
    root = Path(root)
    if camera is not None and not isinstance(camera, PinholeCamera):
        raise ShapeError(f"camera: expected a PinholeCamera, got {type(camera).__name__}")
    if depth_scale is not None:
        try:
            ok = math.isfinite(float(depth_scale)) and float(depth_scale) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"depth_scale: expected a finite number > 0, got {depth_scale!r}")
        depth_scale = float(depth_scale)
        if not DEPTH_SCALE_RANGE[0] <= depth_scale <= DEPTH_SCALE_RANGE[1]:
            raise ConfigError(_depth_scale_problem(depth_scale))
    if camera is not None:
        problem = _camera_problem(camera)
        if problem is not None:
            raise ConfigError(f"camera: implausible intrinsics: {problem[1]}")
    fallback: tuple[PinholeCamera, float] | None = None
    fallback_source = ""
    calib_path = root / CALIBRATION_FILE
    if calib_path.is_file():
        fallback, fallback_source = read_calibration(calib_path), CALIBRATION_FILE
    else:
        key = preset_for_name(root.resolve().name)
        if key is not None:
            preset = INTRINSICS_PRESETS[key]
            fallback, fallback_source = (preset.camera, preset.depth_scale), f"preset:{key}"
    if fallback is None and (camera is None or depth_scale is None):
        missing = " and ".join(n for n, v in (("camera", camera), ("depth_scale", depth_scale)) if v is None)
        raise DataFormatError(
            f"{root}: no calibration for this sequence: there is no {CALIBRATION_FILE} and the folder name "
            f"names no preset ({', '.join(INTRINSICS_PRESETS)}; e.g. 'fr1' or 'icl'). Add {calib_path} with one "
            f"line 'fx fy cx cy depth_scale width height', or pass {missing} explicitly."
        )
    cam_src = "argument" if camera is not None else fallback_source
    scale_src = "argument" if depth_scale is not None else fallback_source
    source = cam_src if cam_src == scale_src else f"{cam_src} (camera), {scale_src} (depth_scale)"
    chosen = camera if camera is not None else fallback[0]
    colour, colour_source = None, None
    if calib_path.is_file():
        colour = read_colour_camera(calib_path, chosen)
        colour_source = CALIBRATION_FILE if colour is not None else None
    if colour is None:
        preset = colour_preset_for(root.resolve().name, chosen)
        if preset is not None:
            colour_source, colour = f"preset:{preset[0]}", preset[1]
    readout, readout_source = readout_for(root)
    return Calibration(chosen, depth_scale if depth_scale is not None else fallback[1], source, colour, colour_source,
                       readout, readout_source)
