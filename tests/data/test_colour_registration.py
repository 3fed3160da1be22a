"""Unregistered colour: the ``colour fx fy cx cy`` calibration line, the 7-Scenes preset, and registration at decode."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests._helpers import copy_tum_frames, data_root
from torchslam.data.calibration import colour_preset_for, colour_to_depth_maps, read_calibration, resolve_calibration
from torchslam.data.tum import TUMSequence, sequence_info
from torchslam.errors import DataFormatError
from torchslam.geometry import PinholeCamera

DEPTH_7SCENES = "585 585 320 240 1000 640 480"


def test_colour_line_is_read_and_the_depth_line_is_unchanged(tmp_path):
    (tmp_path / "calibration.txt").write_text(f"# depth\n{DEPTH_7SCENES}\ncolour 530 531 321 239\n")
    cam, scale = read_calibration(tmp_path / "calibration.txt")
    assert (cam.fx, scale) == (585.0, 1000.0)
    calib = resolve_calibration(tmp_path)
    assert calib.colour_source == "calibration.txt"
    assert (calib.colour_camera.fx, calib.colour_camera.fy, calib.colour_camera.cx, calib.colour_camera.cy) == (530, 531, 321, 239)
    assert (calib.colour_camera.width, calib.colour_camera.height) == (640, 480)


@pytest.mark.parametrize(
    "extra,match",
    [
        ("colour 530 531 321", r"calibration.txt:3: expected 'colour fx fy cx cy' \(4 values\), got 3"),
        ("colour 530 531 321 x", r"calibration.txt:3: not a number"),
        ("colour 530 531 900 239", r"calibration.txt:3: implausible colour intrinsics: principal point cx = 900"),
        ("colour 530 531 321 239\ncolour 530 531 321 239", r"calibration.txt:4: a second 'colour' line \(line 3"),
    ],
)
def test_bad_colour_line_names_file_and_line(tmp_path, extra, match):
    (tmp_path / "calibration.txt").write_text(f"# depth\n{DEPTH_7SCENES}\n{extra}\n")
    with pytest.raises(DataFormatError, match=match):
        resolve_calibration(tmp_path)


def test_seven_scenes_preset_applies_only_to_its_folder_names_and_published_depth_intrinsics():
    cam = PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)
    for name in ("7scenes_redkitchen", "7-Scenes-chess", "data_7_scenes_fire"):
        key, colour = colour_preset_for(name, cam)
        assert key == "7scenes" and (colour.fx, colour.fy) == (532.57, 531.54)
    assert colour_preset_for("tum_fr1_xyz", cam) is None
    assert colour_preset_for("17scenes", cam) is None
    assert colour_preset_for("7scenes_redkitchen", PinholeCamera(580.0, 580.0, 320.0, 240.0, 640, 480)) is None


def test_a_colour_line_takes_precedence_over_the_preset(tmp_path):
    folder = tmp_path / "7scenes_office"
    folder.mkdir()
    (folder / "calibration.txt").write_text(f"{DEPTH_7SCENES}\ncolour 540 540 320 240\n")
    calib = resolve_calibration(folder)
    assert calib.colour_source == "calibration.txt" and calib.colour_camera.fx == 540.0


def test_maps_follow_each_depth_ray_into_the_colour_camera():
    depth = PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)
    colour = PinholeCamera(532.0, 530.0, 318.0, 242.0, 640, 480)
    mx, my = colour_to_depth_maps(depth, colour)
    assert mx.shape == (480, 640) and mx.dtype == np.float32
    for u, v in ((0, 0), (639, 479), (100, 300)):
        x, y = (u - 320.0) / 585.0, (v - 240.0) / 585.0  # the depth pixel's ray
        assert mx[v, u] == pytest.approx(532.0 * x + 318.0, abs=1e-4)
        assert my[v, u] == pytest.approx(530.0 * y + 242.0, abs=1e-4)


def test_seven_scenes_colour_is_registered_at_decode_and_can_be_kept_as_is(tmp_path):
    src = data_root() / "7scenes_redkitchen"
    if not (src / "rgb.txt").is_file():
        pytest.skip(f"7-Scenes sequence not found under {src} (set TORCHSLAM_DATA)")
    folder = copy_tum_frames(src, tmp_path / "7scenes_redkitchen", 2)
    reg = TUMSequence(folder)
    raw = TUMSequence(folder, register_colour=False)
    assert reg.colour_source == "preset:7scenes" and raw.colour_camera is None
    f_reg, f_raw = reg[0], raw[0]
    torch.testing.assert_close(f_reg.depth, f_raw.depth, rtol=0, atol=0)  # depth untouched
    # The registered image is the raw one resampled along the depth rays (same maps, OpenCV).
    bgr = cv2.imread(str(reg.rgb_paths[0]), cv2.IMREAD_COLOR)
    expected = cv2.remap(bgr, *colour_to_depth_maps(reg.camera, reg.colour_camera), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    expected = torch.from_numpy(expected[..., ::-1].copy()).permute(2, 0, 1).float() / 255
    torch.testing.assert_close(f_reg.rgb, expected, rtol=0, atol=1e-6)
    # The colour camera sees wider (fx 532 < 585): registering magnifies the image about its centre.
    assert not torch.allclose(f_reg.rgb, f_raw.rgb)
    assert sequence_info(folder)["colour_registered_with"]["source"] == "preset:7scenes"
    assert sequence_info(folder, register_colour=False)["colour_registered_with"] is None
