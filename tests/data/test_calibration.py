"""Plausibility of intrinsics: calibration.txt, explicit cameras, presets and the synthetic generator."""

import math

import pytest

from torchslam.data.calibration import (
    DEPTH_SCALE_RANGE,
    INTRINSICS_PRESETS,
    MAX_FOV_DEG,
    MIN_FOV_DEG,
    intrinsics_problem,
    read_calibration,
    resolve_calibration,
)
from torchslam.data.synthetic import SyntheticConfig, camera_from_config
from torchslam.errors import ConfigError, DataFormatError
from torchslam.geometry import PinholeCamera

GOOD = "517.3 516.5 318.6 255.3 5000 640 480"


@pytest.mark.parametrize(
    "line,match",
    [
        ("517.3 516.5 900 255.3 5000 640 480", r"principal point cx = 900 px lies outside the image \(-0.5 to 639.5 px"),
        ("517.3 516.5 318.6 -3 5000 640 480", r"principal point cy = -3 px"),
        ("1e-9 516.5 318.6 255.3 5000 640 480", r"fx = 1e-09 px gives a horizontal field of view of 180 degrees"),
        ("517.3 1e7 318.6 255.3 5000 640 480", r"fy = 1e\+07 px gives a vertical field of view of 0.00275 degrees"),
        ("517.3 516.5 318.6 255.3 1e30 640 480", r"depth_scale: expected 1 to 100000 raw depth units per metre .* got 1e\+30"),
        ("517.3 516.5 318.6 255.3 0.01 640 480", r"depth_scale: expected 1 to 100000"),
    ],
)
def test_implausible_calibration_names_file_and_line(tmp_path, line, match):
    path = tmp_path / "calibration.txt"
    path.write_text(f"# fx fy cx cy depth_scale width height\n\n{line}\n")
    with pytest.raises(DataFormatError, match=rf"^{path}:3: implausible calibration: {match}"):
        read_calibration(path)
    # The folder's calibration is read before any image.
    with pytest.raises(DataFormatError, match=rf"{path}:3"):
        resolve_calibration(tmp_path)


def test_plausible_calibration_is_read(tmp_path):
    path = tmp_path / "calibration.txt"
    path.write_text(GOOD + "\n")
    cam, scale = read_calibration(path)
    assert (cam.fx, cam.cx, scale) == (517.3, 318.6, 5000.0)


def test_field_of_view_bounds_are_the_stated_ones():
    # fx = W / (2 tan(fov / 2)) at exactly the stated field-of-view limits passes; just beyond fails.
    for fov in (MIN_FOV_DEG, MAX_FOV_DEG):
        fx = 640 / (2 * math.tan(math.radians(fov) / 2))
        assert intrinsics_problem(fx * (1 + 1e-9) if fov == MAX_FOV_DEG else fx * (1 - 1e-9), 500, 320, 240, 640, 480) is None
        worse = fx * 0.99 if fov == MAX_FOV_DEG else fx * 1.01
        assert intrinsics_problem(worse, 500, 320, 240, 640, 480)[0] == "fx"
    assert intrinsics_problem(500, 500, -0.5, 479.5, 640, 480) is None  # image edges
    assert intrinsics_problem(500, 500, 320, 240, 640, 480, DEPTH_SCALE_RANGE[1] * 1.01)[0] == "depth_scale"


@pytest.mark.parametrize("key", sorted(INTRINSICS_PRESETS))
def test_presets_are_plausible(key):
    p = INTRINSICS_PRESETS[key]
    c = p.camera
    assert intrinsics_problem(c.fx, c.fy, c.cx, c.cy, c.width, c.height, p.depth_scale) is None


def test_explicit_camera_and_depth_scale_are_checked(tmp_path):
    (tmp_path / "calibration.txt").write_text(GOOD + "\n")
    with pytest.raises(ConfigError, match=r"camera: implausible intrinsics: principal point cx = 700"):
        resolve_calibration(tmp_path, camera=PinholeCamera(500, 500, 700, 240, 640, 480))
    with pytest.raises(ConfigError, match=r"depth_scale: expected 1 to 100000"):
        resolve_calibration(tmp_path, depth_scale=1e30)
    assert resolve_calibration(tmp_path, depth_scale=1000).depth_scale == 1000.0


@pytest.mark.parametrize(
    "changes,match",
    [
        ({"fx": 1e-9}, r"SyntheticConfig\.fx: fx = 1e-09 px"),
        ({"cx": 1000.0}, r"SyntheticConfig\.cx: principal point cx = 1000 px"),
        ({"width": 64, "height": 48, "fy": 5000.0}, r"SyntheticConfig\.fy"),
        ({"depth_scale": 1e30}, r"SyntheticConfig\.depth_scale"),
    ],
)
def test_synthetic_intrinsics_are_checked(changes, match):
    with pytest.raises(ConfigError, match=match):
        SyntheticConfig(**changes)


def test_synthetic_default_cameras_are_plausible_at_any_size():
    for w, h in ((640, 480), (64, 48), (17, 9), (4000, 3000)):
        cam = camera_from_config(SyntheticConfig(width=w, height=h))
        assert intrinsics_problem(cam.fx, cam.fy, cam.cx, cam.cy, w, h) is None
