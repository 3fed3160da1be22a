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
    read_readout,
    readout_for,
    readout_preset_for,
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


# --- the sensor's rolling-shutter readout (readout_for) -------------------------------------------


@pytest.mark.parametrize(
    "name,expected",
    [
        ("rgbd_dataset_freiburg1_xyz", (0.03, "preset:freiburg1")),
        ("tum_fr2_desk", (0.03, "preset:freiburg2")),
        ("7scenes_redkitchen", (0.03, "preset:7scenes")),
        ("7-Scenes-chess", (0.03, "preset:7scenes")),
        ("rgbd_dataset_freiburg3_long_office_household", (0.0, None)),  # not a Kinect v1: no record
        ("icl_living_room", (0.0, None)),  # rendered: a global shutter
        ("hololens_dvmvs", (0.0, None)),
    ],
)
def test_readout_follows_the_sensor_a_folder_name_implies(tmp_path, name, expected):
    folder = tmp_path / name
    folder.mkdir()
    assert readout_for(folder) == expected
    assert readout_preset_for(name) == (None if expected[1] is None else expected[1].split(":")[1])


def test_a_readout_line_overrides_the_name_and_leaves_the_camera_as_it_was(tmp_path):
    folder = tmp_path / "tum_fr1_desk"
    folder.mkdir()
    (folder / "calibration.txt").write_text(f"# camera\n{GOOD}\nreadout 0.012\n")
    calib = resolve_calibration(folder)
    assert (calib.readout_time, calib.readout_source) == (0.012, "calibration.txt")
    assert calib.camera == read_calibration(folder / "calibration.txt")[0] and calib.depth_scale == 5000
    (folder / "calibration.txt").write_text(f"readout 0\n{GOOD}\n")  # a global shutter, stated
    assert readout_for(folder) == (0.0, "calibration.txt")
    (folder / "calibration.txt").write_text(f"{GOOD}\n")  # no line: the name's sensor
    assert readout_for(folder) == (0.03, "preset:freiburg1")
    assert read_readout(folder / "calibration.txt") is None


@pytest.mark.parametrize(
    "lines,match",
    [
        ("readout 0.2", r":3: readout: expected seconds from the first image row to the last in \[0, 0.1\].* got 0.2"),
        ("readout -0.01", r":3: readout: expected seconds .* got -0.01"),
        ("readout nan", r":3: readout: expected seconds .* got nan"),
        ("readout fast", r":3: not a number"),
        ("readout", r":3: expected 'readout SECONDS' \(1 value\), got 0 values"),
        ("readout 0.03 0.01", r":3: expected 'readout SECONDS' \(1 value\), got 2 values"),
        ("readout 0.03\nreadout 0.02", r":4: a second 'readout' line \(line 3 already gives one\)"),
    ],
)
def test_a_bad_readout_line_names_file_and_line(tmp_path, lines, match):
    folder = tmp_path / "tum_fr1_xyz"
    folder.mkdir()
    path = folder / "calibration.txt"
    path.write_text(f"# camera\n{GOOD}\n{lines}\n")
    with pytest.raises(DataFormatError, match=rf"^{path}{match}"):
        read_readout(path)
    with pytest.raises(DataFormatError, match=rf"^{path}{match}"):
        resolve_calibration(folder)
