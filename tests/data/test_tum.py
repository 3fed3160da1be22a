"""TUM RGB-D reader: synthetic folders for every rule and bad input, plus the real sequences."""

from __future__ import annotations

import json
import logging
import re
import math
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from torchslam.data import (
    INTRINSICS_PRESETS,
    CorruptImageError,
    ImageFormatError,
    Sequence,
    TUMSequence,
    associate_timestamps,
    preset_for_name,
    read_calibration,
    sequence_info,
)
from torchslam.errors import ConfigError, DataFormatError
from torchslam.geometry import PinholeCamera

W, H = 32, 24
CALIB = "# fx fy cx cy depth_scale width height\n100.0 101.0 15.5 11.5 5000 32 24\n"


def _greedy_reference(a, b, max_gap):
    """Brute-force O(N*M) one-to-one association: all close pairs, closest first, greedily."""
    pairs = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) <= max_gap)
    used_a, used_b, out = set(), set(), []
    for _, i, j in pairs:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def _write_seq(root: Path, rgb_times, depth_times=None, *, calib=CALIB, seed=0, gt=None, accel=None):
    """Write a small TUM folder; return the colour (RGB order) and raw depth arrays written."""
    depth_times = rgb_times if depth_times is None else depth_times
    rng = np.random.default_rng(seed)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgbs, depths = [], []
    lines = ["# color images", "# timestamp filename"]
    for t in rgb_times:
        img = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        assert cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img[:, :, ::-1])
        rgbs.append(img)
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    lines = ["# depth maps", "# timestamp filename"]
    for k, t in enumerate(depth_times):
        raw = rng.integers(1, 30000, size=(H, W), dtype=np.uint16)
        raw[0, :4] = 0
        raw[1, :3] = 65535
        raw[2, 0] = 1000 * (k + 1)  # identifies the depth image in association tests
        assert cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), raw)
        depths.append(raw)
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    if calib is not None:
        (root / "calibration.txt").write_text(calib)
    if gt is not None:
        (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + gt)
    if accel is not None:
        (root / "accelerometer.txt").write_text("# timestamp ax ay az\n" + accel)
    return rgbs, depths


def _times(n, dt=1 / 30, t0=100.0):
    return [round(t0 + k * dt, 6) for k in range(n)]


def _gt_lines(times, rng):
    q = Rotation.random(len(times), random_state=rng).as_quat()
    p = rng.normal(size=(len(times), 3))
    return "".join(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p[k], *q[k])) + "\n" for k, t in enumerate(times)), p, q


# ----------------------------------------------------------------------------------------------
# Decoding, association, selection, prefetch


def test_decode_matches_written_images(tmp_path):
    rgbs, depths = _write_seq(tmp_path / "seq", _times(3))
    seq = TUMSequence(tmp_path / "seq")
    assert isinstance(seq, Sequence)
    assert seq.camera == PinholeCamera(100.0, 101.0, 15.5, 11.5, W, H)
    assert seq.depth_scale == 5000.0 and seq.calibration_source == "calibration.txt"
    for i in range(3):
        f = seq[i]
        assert f.index == i and f.timestamp == pytest.approx(100.0 + i / 30, abs=1e-6)
        assert f.rgb.shape == (3, H, W) and f.rgb.dtype == torch.float32
        expect_rgb = torch.from_numpy(rgbs[i].astype(np.float64) / 255.0).permute(2, 0, 1)
        torch.testing.assert_close(f.rgb.double(), expect_rgb, atol=1e-7, rtol=0)
        raw = depths[i].astype(np.float64)
        expect = np.where((raw == 0) | (raw == 65535), 0.0, raw / 5000.0)
        assert f.depth.shape == (1, H, W) and f.depth.dtype == torch.float32
        torch.testing.assert_close(f.depth[0].double(), torch.from_numpy(expect), atol=1e-6, rtol=1e-7)
        assert (f.depth[0, 1, :3] == 0).all() and f.T_wc is None
    assert torch.equal(seq[-1].rgb, seq[2].rgb)
    with pytest.raises(IndexError, match="out of range"):
        seq[3]


def test_invalid_depth_values_configurable(tmp_path):
    _, depths = _write_seq(tmp_path / "seq", _times(1))
    keep = TUMSequence(tmp_path / "seq", invalid_depth=(0,))[0]
    assert torch.allclose(keep.depth[0, 1, :3], torch.tensor(65535 / 5000.0))
    assert (keep.depth[0, 0, :4] == 0).all()  # raw 0 is always invalid
    both = TUMSequence(tmp_path / "seq")[0]
    assert int((both.depth == 0).sum()) == int(((depths[0] == 0) | (depths[0] == 65535)).sum())


def test_association_one_to_one_with_gaps(tmp_path):
    rgb_t = [10.000, 10.033, 10.066, 10.100, 10.300, 10.400]
    # 10.040 is closest to both 10.033 and 10.050-ish neighbours: only one colour frame may take it;
    # 10.300 has no depth within 0.02 s; 10.420 sits exactly 0.02 s from 10.400.
    depth_t = [9.990, 10.040, 10.058, 10.119, 10.250, 10.420, 11.0]
    _write_seq(tmp_path / "seq", rgb_t, depth_t)
    seq = TUMSequence(tmp_path / "seq")
    ref = _greedy_reference(rgb_t, depth_t, 0.02)
    assert [float(t) for t in seq.timestamps] == pytest.approx([rgb_t[i] for i, _ in ref], abs=1e-9)
    assert [float(t) for t in seq.depth_timestamps] == pytest.approx([depth_t[j] for _, j in ref], abs=1e-9)
    gaps = [abs(rgb_t[i] - depth_t[j]) for i, j in ref]
    a = seq.association
    assert (a.rgb_count, a.depth_count, a.pairs) == (6, 7, len(ref))
    assert (a.dropped_rgb, a.dropped_depth) == (6 - len(ref), 7 - len(ref))
    assert a.max_gap_s == pytest.approx(max(gaps), abs=1e-9) and a.mean_gap_s == pytest.approx(np.mean(gaps), abs=1e-9)
    assert len(set(seq.depth_paths)) == len(seq)  # one-to-one


def test_frame_carries_its_depth_timestamp(tmp_path):
    rgb_t = [10.000, 10.033, 10.066, 10.100]
    depth_t = [9.985, 10.049, 10.052, 10.117]  # offsets -15, +16, -14, +17 ms as on TUM fr1
    _write_seq(tmp_path / "seq", rgb_t, depth_t)
    seq = TUMSequence(tmp_path / "seq")
    ref = _greedy_reference(rgb_t, depth_t, 0.02)
    assert len(seq) == len(ref)
    for k, (i, j) in enumerate(ref):
        f = seq[k]
        assert f.timestamp == pytest.approx(rgb_t[i], abs=1e-9)
        assert f.depth_timestamp == pytest.approx(depth_t[j], abs=1e-9)
        # The decoded depth image is the one written at that stamp (its marker pixel).
        assert float(f.depth[0, 2, 0]) * 5000.0 == pytest.approx(1000 * (j + 1), abs=1e-3)
    for k, (_, j) in enumerate(ref):
        raw = float(seq[k].depth[0, 2, 0]) * 5000.0
        assert raw == pytest.approx(1000 * (j + 1), rel=1e-6)


def test_stride_and_range_apply_after_association(tmp_path):
    rgbs, _ = _write_seq(tmp_path / "seq", _times(9))
    full = TUMSequence(tmp_path / "seq")
    sub = TUMSequence(tmp_path / "seq", stride=3, start=1, end=8)
    assert torch.equal(sub.timestamps, full.timestamps[1:8:3])
    assert len(sub) == 3
    for k, i in enumerate(range(1, 8, 3)):
        f = sub[k]
        assert f.index == k
        torch.testing.assert_close(f.rgb, full[i].rgb)
        torch.testing.assert_close(f.rgb, torch.from_numpy(rgbs[i]).permute(2, 0, 1).float() / 255.0)


@pytest.mark.parametrize("prefetch", [1, 2, 5])
def test_prefetch_yields_same_frames_in_order(tmp_path, prefetch):
    _write_seq(tmp_path / "seq", _times(7))
    plain = list(TUMSequence(tmp_path / "seq"))
    fetched = list(TUMSequence(tmp_path / "seq", prefetch=prefetch))
    assert [f.index for f in fetched] == list(range(7))
    for a, b in zip(plain, fetched):
        assert a.timestamp == b.timestamp
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)


def test_prefetch_thread_stops_when_consumer_stops(tmp_path):
    _write_seq(tmp_path / "seq", _times(6))
    seq = TUMSequence(tmp_path / "seq", prefetch=2)
    it = iter(seq)
    first = next(it)
    assert first.index == 0
    it.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("torchslam-prefetch")]


def test_ground_truth_interpolated_inside_gaps_only(tmp_path):
    rng = np.random.default_rng(3)
    # 100 Hz ground truth with a 0.13 s hole (interpolated) and a 0.5 s hole (not interpolated).
    gt_t = [round(99.9 + 0.01 * k, 6) for k in range(20)] + [round(100.22 + 0.01 * k, 6) for k in range(20)]
    gt_t += [round(100.91 + 0.01 * k, 6) for k in range(10)]
    gt_text, p, q = _gt_lines(gt_t, rng)
    frame_t = [100.0, 100.05, 100.095, 100.15, 100.2, 100.3, 100.6, 100.95, 101.2]
    _write_seq(tmp_path / "seq", frame_t, gt=gt_text)
    seq = TUMSequence(tmp_path / "seq")
    gt_arr = np.asarray(gt_t)
    expect_valid = []
    for k, t in enumerate(frame_t):
        hi = int(np.searchsorted(gt_arr, t))
        inside = gt_arr[0] <= t <= gt_arr[-1]
        valid = inside and gt_arr[max(hi, 1)] - gt_arr[max(hi, 1) - 1] <= 0.2
        expect_valid.append(valid)
        f = seq[k]
        if not valid:
            assert f.T_wc is None
            continue
        lo, hi = max(hi, 1) - 1, max(hi, 1)
        alpha = (t - gt_arr[lo]) / (gt_arr[hi] - gt_arr[lo])
        R = Slerp([0.0, 1.0], Rotation.from_quat(q[[lo, hi]]))([alpha]).as_matrix()[0]
        pos = p[lo] + alpha * (p[hi] - p[lo])
        np.testing.assert_allclose(f.T_wc[:3, :3].numpy(), R, atol=1e-7)
        np.testing.assert_allclose(f.T_wc[:3, 3].numpy(), pos, atol=1e-7)
    assert seq.gt_valid.tolist() == expect_valid
    assert expect_valid == [True, True, True, True, True, True, False, True, False]
    assert torch.equal(seq.groundtruth.timestamps, seq.timestamps[seq.gt_valid])
    info = sequence_info(tmp_path / "seq")
    assert info["gt_poses"] == 50 and info["gt_frames_covered"] == 7
    assert info["gt_frames_interpolated_across_gap"] == 3  # 100.095, 100.15, 100.2 sit in the 0.13 s hole
    assert info["gt_largest_gap_s"] == pytest.approx(0.5, abs=1e-6)
    json.dumps(info)


def test_no_groundtruth_and_accelerometer(tmp_path):
    accel = "100.0 0.1 9.8 -0.2\n100.001 0.2 9.7 -0.1\n100.002 0.3 9.6 0.0\n"
    _write_seq(tmp_path / "seq", _times(2), accel=accel)
    seq = TUMSequence(tmp_path / "seq")
    assert seq.groundtruth is None and not seq.gt_valid.any()
    t, v = seq.accelerometer
    assert t.dtype == torch.float64 and v.shape == (3, 3)
    np.testing.assert_allclose(v.numpy(), np.loadtxt(tmp_path / "seq" / "accelerometer.txt")[:, 1:])
    info = sequence_info(tmp_path / "seq")
    assert info["accelerometer_samples"] == 3 and info["gt_poses"] == 0 and info["gt_largest_gap_s"] is None


def test_associate_timestamps_matches_brute_force():
    rng = np.random.default_rng(7)
    for trial in range(30):
        n, m = rng.integers(0, 40, size=2)
        # Rounded to milliseconds so that equal gaps (ties) occur.
        a = np.sort(np.unique(np.round(rng.uniform(0, 1, size=n), 3)))
        b = np.sort(np.unique(np.round(rng.uniform(0, 1, size=m), 3)))
        gap = float(rng.choice([0.0, 0.005, 0.02, 0.1]))
        ia, ib = associate_timestamps(torch.from_numpy(a), torch.from_numpy(b), gap)
        got = list(zip(ia.tolist(), ib.tolist()))
        assert got == _greedy_reference(a.tolist(), b.tolist(), gap), f"trial {trial}"


# ----------------------------------------------------------------------------------------------
# Calibration: presets, calibration.txt, arguments


@pytest.mark.parametrize(
    "folder, key",
    [
        ("rgbd_dataset_freiburg1_xyz", "freiburg1"),
        ("tum_fr1_xyz", "freiburg1"),
        ("rgbd_dataset_freiburg2_desk", "freiburg2"),
        ("FR3_office", "freiburg3"),
        ("icl_living_room_kt0", "icl_nuim"),
        ("fr12_room", None),
        ("africa", None),
        ("bicycle", None),
    ],
)
def test_preset_from_folder_name(tmp_path, folder, key):
    assert preset_for_name(folder) == key
    _write_seq(tmp_path / folder, _times(1), calib=None)
    if key is None:
        with pytest.raises(DataFormatError, match=r"no calibration.*calibration\.txt"):
            TUMSequence(tmp_path / folder)
        return
    seq = TUMSequence(tmp_path / folder)
    assert seq.camera == INTRINSICS_PRESETS[key].camera and seq.depth_scale == 5000.0
    assert seq.calibration_source == f"preset:{key}"
    with pytest.raises(DataFormatError, match="colour image is 32x24.*640x480"):
        seq[0]


def test_preset_values():
    cams = {k: v.camera for k, v in INTRINSICS_PRESETS.items()}
    assert (cams["freiburg1"].fx, cams["freiburg1"].fy, cams["freiburg1"].cx, cams["freiburg1"].cy) == (517.3, 516.5, 318.6, 255.3)
    assert (cams["freiburg2"].fx, cams["freiburg2"].cy) == (520.9, 249.7)
    assert (cams["freiburg3"].fy, cams["freiburg3"].cx) == (539.2, 320.1)
    assert (cams["icl_nuim"].fx, cams["icl_nuim"].fy, cams["icl_nuim"].cx) == (481.2, 480.0, 319.5)
    assert all(v.depth_scale == 5000.0 and (v.camera.width, v.camera.height) == (640, 480) for v in INTRINSICS_PRESETS.values())


def test_preset_distortion():
    """freiburg1/2 images are distributed distorted (published k1 k2 p1 p2 k3); fr3 and ICL are not."""
    cams = {k: v.camera for k, v in INTRINSICS_PRESETS.items()}
    assert cams["freiburg1"].distortion == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    assert cams["freiburg2"].distortion == (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    assert cams["freiburg3"].distortion is None and cams["icl_nuim"].distortion is None
    assert cams["freiburg1"].has_distortion and not cams["freiburg3"].has_distortion


def test_real_fr1_sequence_carries_the_preset_distortion(shared_data):
    seq = TUMSequence(shared_data / "tum_fr1_xyz", end=2)
    assert seq.calibration_source == "preset:freiburg1"
    assert seq.camera.distortion == INTRINSICS_PRESETS["freiburg1"].camera.distortion


def test_calibration_file_and_arguments_take_precedence(tmp_path):
    _write_seq(tmp_path / "tum_fr2_x", _times(1))  # has calibration.txt despite the fr2 name
    seq = TUMSequence(tmp_path / "tum_fr2_x")
    assert seq.calibration_source == "calibration.txt" and seq.camera.fx == 100.0
    cam = PinholeCamera(50.0, 50.0, 16.0, 12.0, W, H)
    over = TUMSequence(tmp_path / "tum_fr2_x", camera=cam)
    assert over.camera == cam and over.depth_scale == 5000.0
    assert over.calibration_source == "argument (camera), calibration.txt (depth_scale)"
    both = TUMSequence(tmp_path / "tum_fr2_x", camera=cam, depth_scale=1000.0)
    assert both.calibration_source == "argument" and both.depth_scale == 1000.0
    _write_seq(tmp_path / "plain", _times(1), calib=None)
    assert TUMSequence(tmp_path / "plain", camera=cam, depth_scale=5000).camera == cam
    with pytest.raises(DataFormatError, match=r"plain: no calibration.*depth_scale"):
        TUMSequence(tmp_path / "plain", camera=cam)


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("# c\n100 100 16 12 5000 32\n", 2, "expected 7 values"),
        ("100 100 16 12 5000 32 24 0.1\n", 1, "expected 7 values.*4, 5 or 8 distortion coefficients.*got 8"),
        ("100 100 16 12 5000 32 24 0.1 0.2 0.3 0.4 0.5 0.6\n", 1, "got 13"),
        ("100 100 16 12 5000 32 24 0.1 x 0 0\n", 1, "not a number"),
        ("100 100 16 12 5000 32 24 0.1 inf 0 0\n", 1, "NaN or infinite"),
        ("100 100 16 x 5000 32 24\n", 1, "not a number"),
        ("#\n\n100 100 16 12 5000 32.5 24\n", 3, "must be integers"),
        ("100 -100 16 12 5000 32 24\n", 1, "focal lengths must be positive"),
        ("100 100 16 12 0 32 24\n", 1, "depth_scale must be > 0"),
        ("100 100 nan 12 5000 32 24\n", 1, "NaN or infinite"),
        ("100 100 16 12 5000 32 24\n# again\n100 100 16 12 5000 32 24\n", 3, "a second calibration line"),
        ("# only comments\n", None, "no calibration line"),
    ],
)
def test_read_calibration_errors(tmp_path, text, line, match):
    path = tmp_path / "calibration.txt"
    path.write_text(text)
    where = f"calibration.txt:{line}: " if line else "calibration.txt: "
    with pytest.raises(DataFormatError, match=re.escape(where) + ".*" + match):
        read_calibration(path)


def test_read_calibration_values(tmp_path):
    path = tmp_path / "calibration.txt"
    path.write_text("# fx fy cx cy depth_scale width height\n585 586 320 240 1000 640 480\n")
    cam, scale = read_calibration(path)
    assert cam == PinholeCamera(585.0, 586.0, 320.0, 240.0, 640, 480) and scale == 1000.0
    assert cam.distortion is None


@pytest.mark.parametrize("coeffs", [(0.1, -0.2, 0.003, -0.004), (0.1, -0.2, 0.003, -0.004, 0.5), (0.1, -0.2, 0.003, -0.004, 0.5, 0.01, 0.02, 0.03)])
def test_read_calibration_optional_distortion(tmp_path, coeffs):
    path = tmp_path / "calibration.txt"
    path.write_text("# fx fy cx cy depth_scale width height k1 k2 p1 p2 ...\n585 586 320 240 1000 640 480 " + " ".join(map(str, coeffs)) + "\n")
    cam, scale = read_calibration(path)
    assert cam == PinholeCamera(585.0, 586.0, 320.0, 240.0, 640, 480, coeffs) and scale == 1000.0
    assert cam.distortion == coeffs


# ----------------------------------------------------------------------------------------------
# Bad input


def test_not_a_sequence_folder(tmp_path):
    with pytest.raises(DataFormatError, match="not a folder"):
        TUMSequence(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match=r"not a TUM RGB-D sequence: missing rgb\.txt and depth\.txt"):
        TUMSequence(tmp_path / "empty")
    _write_seq(tmp_path / "seq", _times(2))
    (tmp_path / "seq" / "depth.txt").unlink()
    with pytest.raises(DataFormatError, match=r"missing depth\.txt \("):
        TUMSequence(tmp_path / "seq")


def test_list_naming_missing_image_fails_at_construction(tmp_path):
    _write_seq(tmp_path / "seq", _times(4))
    missing = tmp_path / "seq" / "depth" / f"{_times(4)[2]:.6f}.png"
    missing.unlink()
    with pytest.raises(DataFormatError, match=re.escape(f"depth.txt:5: listed image {missing} does not exist")):
        TUMSequence(tmp_path / "seq")


def _corrupt(path: Path, how: str) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if how == "truncated" else b"this is not an image at all")


@pytest.mark.parametrize("how", ["truncated", "garbage"])
@pytest.mark.parametrize("which", ["rgb", "depth"])
@pytest.mark.parametrize("prefetch", [0, 2])
def test_corrupt_image_skipped_in_iteration_raised_in_getitem(tmp_path, caplog, how, which, prefetch):
    _write_seq(tmp_path / "seq", _times(5))
    bad = tmp_path / "seq" / which / f"{_times(5)[2]:.6f}.png"
    _corrupt(bad, how)
    seq = TUMSequence(tmp_path / "seq", prefetch=prefetch)
    with caplog.at_level(logging.WARNING, logger="torchslam.data.tum"):
        frames = list(seq)
    assert [f.index for f in frames] == [0, 1, 3, 4]
    assert len(seq.skipped) == 1 and seq.skipped[0][0] == 2 and str(bad) in seq.skipped[0][1]
    assert any("skipping frame 2" in r.getMessage() and str(bad) in r.getMessage() for r in caplog.records)
    reason = "truncated image file" if how == "truncated" else "cannot decode image"
    assert reason in seq.skipped[0][1]
    with pytest.raises(CorruptImageError, match=re.escape(str(bad)) + f".*{which}.txt:5.*{reason}"):
        seq[2]
    assert isinstance(CorruptImageError("x"), DataFormatError)


def test_truncated_jpeg_colour_detected(tmp_path):
    _write_seq(tmp_path / "seq", _times(2))
    lines = (tmp_path / "seq" / "rgb.txt").read_text().replace(".png", ".jpg")
    (tmp_path / "seq" / "rgb.txt").write_text(lines)
    for t in _times(2):
        img = cv2.imread(str(tmp_path / "seq" / "rgb" / f"{t:.6f}.png"))
        cv2.imwrite(str(tmp_path / "seq" / "rgb" / f"{t:.6f}.jpg"), img)
    seq = TUMSequence(tmp_path / "seq")
    assert seq[0].rgb.shape == (3, H, W)
    _corrupt(tmp_path / "seq" / "rgb" / f"{_times(2)[1]:.6f}.jpg", "truncated")
    with pytest.raises(CorruptImageError, match=r"\.jpg \(rgb\.txt:4\): truncated image file"):
        seq[1]


@pytest.mark.parametrize("prefetch", [0, 3])
def test_depth_not_16_bit(tmp_path, prefetch):
    _write_seq(tmp_path / "seq", _times(3))
    bad = tmp_path / "seq" / "depth" / f"{_times(3)[1]:.6f}.png"
    cv2.imwrite(str(bad), np.full((H, W), 7, dtype=np.uint8))
    seq = TUMSequence(tmp_path / "seq", prefetch=prefetch)
    with pytest.raises(DataFormatError, match=re.escape(str(bad)) + r".*single-channel 16-bit.*uint8"):
        seq[1]
    with pytest.raises(ImageFormatError, match="16-bit"):
        seq[1]
    # In iteration a frame in the middle is skipped with its reason (see the tests below).
    assert [f.index for f in seq] == [0, 2] and "16-bit" in seq.skipped[0][1]
    cv2.imwrite(str(bad), np.full((H, W, 3), 7, dtype=np.uint16))
    with pytest.raises(DataFormatError, match=r"uint16 with 3 channel"):
        seq[1]


@pytest.mark.parametrize("prefetch", [0, 2])
def test_wrong_size_or_format_in_the_middle_is_skipped_with_its_reason(tmp_path, caplog, prefetch):
    _write_seq(tmp_path / "seq", _times(6))
    depth8 = tmp_path / "seq" / "depth" / f"{_times(6)[2]:.6f}.png"
    cv2.imwrite(str(depth8), np.full((H, W), 7, dtype=np.uint8))
    small = tmp_path / "seq" / "rgb" / f"{_times(6)[4]:.6f}.png"
    cv2.imwrite(str(small), np.ones((H // 2, W // 2, 3), dtype=np.uint8))
    seq = TUMSequence(tmp_path / "seq", prefetch=prefetch)
    with caplog.at_level(logging.WARNING, logger="torchslam.data.tum"):
        frames = list(seq)
    assert [f.index for f in frames] == [0, 1, 3, 5]
    assert [i for i, _ in seq.skipped] == [2, 4]
    assert str(depth8) in seq.skipped[0][1] and "single-channel 16-bit" in seq.skipped[0][1]
    assert str(small) in seq.skipped[1][1] and "colour image is 16x12" in seq.skipped[1][1]
    assert sum("skipping frame" in r.getMessage() for r in caplog.records) == 2
    # The same file in the first frame means the folder and its calibration disagree: raised.
    cv2.imwrite(str(tmp_path / "seq" / "rgb" / f"{_times(6)[0]:.6f}.png"), np.ones((H // 2, W // 2, 3), dtype=np.uint8))
    with pytest.raises(ImageFormatError, match=r"rgb\.txt:3\): colour image is 16x12"):
        list(TUMSequence(tmp_path / "seq", prefetch=prefetch))


def test_image_size_mismatch(tmp_path):
    _write_seq(tmp_path / "seq", _times(2))
    bad = tmp_path / "seq" / "depth" / f"{_times(2)[0]:.6f}.png"
    cv2.imwrite(str(bad), np.ones((H // 2, W // 2), dtype=np.uint16))
    with pytest.raises(DataFormatError, match=r"depth\.txt:3\): depth image is 16x12.*calibration\.txt\) says 32x24"):
        TUMSequence(tmp_path / "seq")[0]
    bad = tmp_path / "seq" / "rgb" / f"{_times(2)[1]:.6f}.png"
    cv2.imwrite(str(bad), np.ones((H, W + 1, 3), dtype=np.uint8))
    with pytest.raises(DataFormatError, match=r"rgb\.txt:4\): colour image is 33x24"):
        TUMSequence(tmp_path / "seq")[1]


@pytest.mark.parametrize("listname", ["rgb.txt", "depth.txt", "accelerometer.txt"])
@pytest.mark.parametrize("kind", ["duplicate", "decreasing"])
def test_non_monotonic_timestamps(tmp_path, listname, kind):
    accel = "100.0 0 0 9.8\n100.01 0 0 9.8\n100.02 0 0 9.8\n100.03 0 0 9.8\n"
    _write_seq(tmp_path / "seq", _times(4), accel=accel)
    path = tmp_path / "seq" / listname
    lines = path.read_text().splitlines()
    data = [k for k, s in enumerate(lines) if not s.startswith("#")]
    a, b = data[1], data[2]
    if kind == "duplicate":
        lines[b] = lines[a].split()[0] + " " + " ".join(lines[b].split()[1:])
    else:
        lines[a], lines[b] = lines[b], lines[a]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=re.escape(f"{listname}:{b + 1}: {kind} timestamp")):
        TUMSequence(tmp_path / "seq")


@pytest.mark.parametrize("bad, what", [("nan", "NaN or infinite"), ("inf", "NaN or infinite"), ("1.0 2.0", "expected 8 values")])
def test_bad_groundtruth_rows(tmp_path, bad, what):
    rows = "100.0 0 0 0 0 0 0 1\n100.01 0 0 0 0 0 0 1\n"
    row3 = f"100.02 {bad} 0 0 0 0 0 1\n" if bad != "1.0 2.0" else "1.0 2.0\n"
    _write_seq(tmp_path / "seq", _times(2), gt=rows + row3)
    with pytest.raises(DataFormatError, match=re.escape("groundtruth.txt:4: ") + what):
        TUMSequence(tmp_path / "seq")


@pytest.mark.parametrize(
    "line, match",
    [
        ("100.5", "expected 2 values 'timestamp filename', got 1"),
        ("100.5 rgb/a.png extra", "expected 2 values 'timestamp filename', got 3"),
        ("abc rgb/a.png", "timestamp is not a number"),
        ("nan rgb/a.png", "timestamp is NaN or infinite"),
    ],
)
def test_malformed_list_line(tmp_path, line, match):
    _write_seq(tmp_path / "seq", _times(2))
    path = tmp_path / "seq" / "rgb.txt"
    path.write_text(path.read_text() + line + "\n")
    with pytest.raises(DataFormatError, match=re.escape("rgb.txt:5: ") + match):
        TUMSequence(tmp_path / "seq")


def test_malformed_accelerometer_line(tmp_path):
    _write_seq(tmp_path / "seq", _times(2), accel="100.0 0 0 9.8\n100.01 0 x 9.8\n")
    with pytest.raises(DataFormatError, match=re.escape("accelerometer.txt:3: not a number")):
        TUMSequence(tmp_path / "seq")


def test_empty_sequence(tmp_path):
    _write_seq(tmp_path / "far", _times(3), _times(3, t0=105.0))
    with pytest.raises(DataFormatError, match=r"empty sequence.*max_gap=0\.02.*4\.9\d+ s apart"):
        TUMSequence(tmp_path / "far")
    _write_seq(tmp_path / "none", [])
    with pytest.raises(DataFormatError, match="empty sequence.*lists is empty"):
        TUMSequence(tmp_path / "none")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"stride": 0}, "stride: expected an integer >= 1, got 0"),
        ({"stride": 1.5}, "stride: expected an integer"),
        ({"stride": True}, "stride: expected an integer"),
        ({"start": -1}, "start: expected an integer >= 0"),
        ({"start": 4}, "start: 4 is past the last of the 4 associated frames"),
        ({"end": 5}, "end: 5 is past the 4 associated frames"),
        ({"start": 2, "end": 2}, r"end: 2 must be greater than start \(2\)"),
        ({"end": 0}, "end: expected an integer >= 1"),
        ({"prefetch": -1}, "prefetch: expected an integer >= 0"),
        ({"max_gap": -0.1}, "max_gap: expected a finite number"),
        ({"max_gap": float("nan")}, "max_gap: expected a finite number"),
        ({"gt_max_gap": 0}, "gt_max_gap: expected a finite number of seconds > 0"),
        ({"invalid_depth": (0, 70000)}, r"invalid_depth: values must lie in \[0, 65535\]"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, match):
    _write_seq(tmp_path / "seq", _times(4))
    with pytest.raises(ConfigError, match=match):
        TUMSequence(tmp_path / "seq", **kwargs)


# ----------------------------------------------------------------------------------------------
# Real sequences


def _list_stamps(path: Path) -> np.ndarray:
    return np.loadtxt(path, usecols=0, comments="#", dtype=np.float64)


def test_real_tum_fr1_xyz(shared_data):
    root = shared_data / "tum_fr1_xyz"
    seq = TUMSequence(root)
    assert seq.calibration_source == "preset:freiburg1" and seq.camera == INTRINSICS_PRESETS["freiburg1"].camera
    rgb_t, depth_t = _list_stamps(root / "rgb.txt"), _list_stamps(root / "depth.txt")
    assert (seq.association.rgb_count, seq.association.depth_count) == (210, 210) == (rgb_t.size, depth_t.size)
    ref = _greedy_reference(rgb_t.tolist(), depth_t.tolist(), 0.02)
    assert len(seq) == seq.association.pairs == len(ref)
    np.testing.assert_array_equal(seq.timestamps.numpy(), rgb_t[[i for i, _ in ref]])
    # Every frame has ground truth (the file spans the images with about 1 s of margin).
    assert bool(seq.gt_valid.all()) and len(seq.groundtruth) == len(seq)

    gt = np.loadtxt(root / "groundtruth.txt", comments="#")
    k = int(np.argmax(np.diff(gt[:, 0])))
    t0, t1 = gt[k, 0], gt[k + 1, 0]
    assert t1 - t0 == pytest.approx(0.110, abs=1e-3)
    in_hole = np.flatnonzero((seq.timestamps.numpy() > t0) & (seq.timestamps.numpy() < t1))
    assert in_hole.size >= 2
    slerp = Slerp([t0, t1], Rotation.from_quat(gt[[k, k + 1], 4:8]))
    for i in in_hole:
        t = float(seq.timestamps[i])
        T = seq.groundtruth.T_wc[i].numpy()
        alpha = (t - t0) / (t1 - t0)
        np.testing.assert_allclose(T[:3, 3], gt[k, 1:4] + alpha * (gt[k + 1, 1:4] - gt[k, 1:4]), atol=1e-9)
        np.testing.assert_allclose(T[:3, :3], slerp([t]).as_matrix()[0], atol=1e-9)
        # Close to both neighbours: within the few centimetres the camera moves across the hole.
        for j in (k, k + 1):
            assert np.linalg.norm(T[:3, 3] - gt[j, 1:4]) <= np.linalg.norm(gt[k + 1, 1:4] - gt[k, 1:4]) + 1e-12
            angle = (Rotation.from_matrix(T[:3, :3]).inv() * Rotation.from_quat(gt[j, 4:8])).magnitude()
            assert angle <= (Rotation.from_quat(gt[k, 4:8]).inv() * Rotation.from_quat(gt[k + 1, 4:8])).magnitude() + 1e-9

    info = sequence_info(root)
    json.dumps(info)
    assert info["frames"] == len(seq) and info["gt_coverage_fraction"] == 1.0
    assert info["gt_frames_interpolated_across_gap"] == in_hole.size
    assert info["gt_largest_gap_s"] == pytest.approx(t1 - t0, abs=1e-9)
    acc = np.loadtxt(root / "accelerometer.txt", comments="#")
    assert info["accelerometer_samples"] == acc.shape[0]
    np.testing.assert_array_equal(seq.accelerometer[1].numpy(), acc[:, 1:])

    f = seq[10]
    raw = cv2.imread(str(seq.depth_paths[10]), cv2.IMREAD_UNCHANGED)
    bgr = cv2.imread(str(seq.rgb_paths[10]), cv2.IMREAD_COLOR)
    np.testing.assert_allclose(f.depth[0].numpy(), raw.astype(np.float64) / 5000.0, rtol=1e-6)
    np.testing.assert_allclose(f.rgb.permute(1, 2, 0).numpy(), bgr[:, :, ::-1] / 255.0, atol=1e-6)
    torch.testing.assert_close(f.T_wc, seq.groundtruth.T_wc[10])


def test_real_7scenes_invalid_65535(shared_data):
    root = shared_data / "7scenes_redkitchen"
    seq = TUMSequence(root)
    cam, scale = read_calibration(root / "calibration.txt")
    assert seq.calibration_source == "calibration.txt" and seq.camera == cam and seq.depth_scale == scale == 1000.0
    assert len(seq) == 300 and bool(seq.gt_valid.all())
    raw = cv2.imread(str(seq.depth_paths[33]), cv2.IMREAD_UNCHANGED)
    sentinel = raw == 65535
    assert sentinel.sum() > 0
    depth = seq[33].depth[0].numpy()
    assert (depth[sentinel] == 0).all()
    ok = (raw != 0) & ~sentinel
    np.testing.assert_allclose(depth[ok], raw[ok] / 1000.0, rtol=1e-6)
    kept = TUMSequence(root, invalid_depth=(0,), start=33, end=34)[0].depth[0].numpy()
    np.testing.assert_allclose(kept[sentinel], 65.535, rtol=1e-6)


def test_real_hololens_size(shared_data):
    root = shared_data / "hololens_dvmvs"
    seq = TUMSequence(root, stride=7)
    assert (seq.camera.width, seq.camera.height) == (540, 360)
    assert len(seq) == len(range(0, 50, 7))
    f = seq[-1]
    assert f.rgb.shape == (3, 360, 540) and f.depth.shape == (1, 360, 540)
    assert f.T_wc is not None and seq.accelerometer is None
    info = sequence_info(root)
    assert info["image_size"] == {"width": 540, "height": 360} and info["intrinsics_source"] == "calibration.txt"
    assert math.isclose(info["depth_scale"], 1000.0)


# ----------------------------------------------------------------------------------------------
# imu.txt

G = 9.81
# A camera looking along world +x, held upright: camera x right = world -y, y down = world -z.
_R_UPRIGHT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _imu_lines(times, gyro=(0.0, 0.0, 0.0), R_wc=_R_UPRIGHT):
    accel = R_wc.T @ np.array([0.0, 0.0, G])  # at rest: +g along the camera's up direction
    return "".join(f"{t:.6f} {gyro[0]} {gyro[1]} {gyro[2]} {accel[0]:.9f} {accel[1]:.9f} {accel[2]:.9f}\n" for t in times)


def _write_imu(root: Path, body: str) -> None:
    (root / "imu.txt").write_text("# imu data\n# timestamp gx gy gz ax ay az\n\n" + body)


def test_imu_file_is_read_and_drives_an_attitude_stream(tmp_path):
    from torchslam.imu import ImuData

    root = tmp_path / "seq"
    _write_seq(root, _times(4))
    imu_t = [round(99.9 + k * 0.005, 6) for k in range(60)]
    rate = 0.5  # rad/s about the camera's y axis, which is vertical: the specific force stays put
    _write_imu(root, _imu_lines(imu_t, gyro=(0.0, rate, 0.0)))
    seq = TUMSequence(root)
    assert isinstance(seq.imu, ImuData) and len(seq.imu) == 60
    np.testing.assert_allclose(seq.imu.timestamps.numpy(), imu_t)
    np.testing.assert_allclose(seq.imu.gyro[:, 1].numpy(), rate)
    np.testing.assert_allclose(seq.imu.accel.norm(dim=-1).numpy(), G, rtol=1e-9)
    assert seq.attitude is not None and seq.attitude.source == "imu" and len(seq.attitude) == 60
    # No ground truth: levelled by gravity, so the camera's up (its -y) is the world's +z ...
    R = seq.attitude.R_wc
    np.testing.assert_allclose((R[:, :, 1] @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).numpy(), -1.0, atol=1e-6)
    # ... and the gyro turns it about that axis by rate * (t_last - t_first).
    rel = R[0].T @ R[-1]
    angle = math.atan2(float(rel[0, 2]), float(rel[0, 0]))
    assert angle == pytest.approx(rate * (imu_t[-1] - imu_t[0]), abs=1e-6)
    assert sequence_info(root)["imu_samples"] == 60
    assert TUMSequence(tmp_path / "seq", stride=2).imu.timestamps.shape == (60,)  # the stream is kept whole


def test_imu_start_attitude_comes_from_a_z_up_ground_truth_only(tmp_path, caplog):
    from torchslam.geometry import quat_xyzw_to_rotmat

    times = _times(4)
    yaw = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    R_wc = yaw @ _R_UPRIGHT
    q = Rotation.from_matrix(R_wc).as_quat()
    gt = "".join(f"{t:.6f} 0 0 0 " + " ".join(f"{v:.9f}" for v in q) + "\n" for t in [99.85, 99.95, *times])
    root = tmp_path / "zup"
    _write_seq(root, times, gt=gt)
    _write_imu(root, _imu_lines([round(99.9 + k * 0.005, 6) for k in range(40)], R_wc=R_wc))
    seq = TUMSequence(root)
    np.testing.assert_allclose(seq.attitude.R_wc[0].numpy(), R_wc, atol=1e-6)  # the ground truth's heading
    # A ground truth whose world is not z-up (here y-down, as a first-camera world is) is not used.
    R_bad = Rotation.from_euler("x", 90, degrees=True).as_matrix() @ R_wc
    q_bad = Rotation.from_matrix(R_bad).as_quat()
    gt_bad = "".join(f"{t:.6f} 0 0 0 " + " ".join(f"{v:.9f}" for v in q_bad) + "\n" for t in [99.85, 99.95, *times])
    root = tmp_path / "ydown"
    _write_seq(root, times, gt=gt_bad)
    _write_imu(root, _imu_lines([round(99.9 + k * 0.005, 6) for k in range(40)], R_wc=R_wc))
    with caplog.at_level(logging.WARNING, logger="torchslam.data.tum"):
        seq = TUMSequence(root)
    assert "not z-up" in caplog.text and "imu.txt" in caplog.text
    up = seq.attitude.R_wc[0] @ quat_xyzw_to_rotmat(torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))
    np.testing.assert_allclose(up[:, 1].numpy(), [0.0, 0.0, -1.0], atol=1e-6)  # levelled by gravity instead


def test_imu_start_attitude_from_ground_truth_when_the_stream_starts_accelerating(tmp_path, caplog):
    # The camera (still upright, 40 degrees of heading) swings along world y at 6 m/s^2 from the
    # swing's peak: its first 0.1 s of specific force shows an up 31 degrees off +z, more than the
    # 20 allowed, but its first seconds, whole swings, show gravity's. The z-up ground truth starts
    # the filter, as it did before the stream moved.
    times = _times(4)
    R_wc = Rotation.from_euler("z", 40, degrees=True).as_matrix() @ _R_UPRIGHT
    q = Rotation.from_matrix(R_wc).as_quat()
    gt = "".join(f"{t:.6f} 0 0 0 " + " ".join(f"{v:.9f}" for v in q) + "\n" for t in [99.85, 99.95, *times])
    root = tmp_path / "swing"
    _write_seq(root, times, gt=gt)
    imu_t = [round(99.9 + k * 0.005, 6) for k in range(1201)]  # 6 s, 3 swings
    lines = []
    for t in imu_t:
        f = R_wc.T @ np.array([0.0, 6.0 * math.cos(math.pi * (t - 99.9)), G])
        lines.append(f"{t:.6f} 0 0 0 {f[0]:.9f} {f[1]:.9f} {f[2]:.9f}\n")
    _write_imu(root, "".join(lines))
    with caplog.at_level(logging.WARNING, logger="torchslam.data.tum"):
        seq = TUMSequence(root)
    assert "not z-up" not in caplog.text
    np.testing.assert_allclose(seq.attitude.R_wc[0].numpy(), R_wc, atol=1e-6)
    # Without the ground truth the filter is levelled by the same seconds: the camera's up is +z.
    (root / "groundtruth.txt").unlink()
    R0 = TUMSequence(root).attitude.R_wc[0].numpy()
    assert R0[:, 1] @ np.array([0.0, 0.0, -1.0]) > math.cos(math.radians(0.1))


@pytest.mark.parametrize(
    "scale, match",
    [(1 / G, "median magnitude is 1, expected about 9.81 (ax ay az in m/s^2, gravity included) (in g? multiply ax ay az by 9.81)"),
     (0.0, "median magnitude is 0, expected about 9.81"), (3.0, "median magnitude is 29.4, expected about 9.81")],
)
def test_imu_file_in_other_units_is_refused(tmp_path, scale, match):
    # The accelerometer logged in g (as many devices do), zeroed, or tripled: the file is named.
    _write_seq(tmp_path / "seq", _times(2))
    body = "".join(f"{100 + k * 0.005:.6f} 0 0 0 0 {-G * scale * math.cos(0.01 * k):.6f} {G * scale * math.sin(0.01 * k):.6f}\n" for k in range(20))
    _write_imu(tmp_path / "seq", body)
    with pytest.raises(DataFormatError, match=re.escape(match)) as err:
        TUMSequence(tmp_path / "seq")
    assert "imu.txt" in str(err.value)
    # Moving samples around gravity's magnitude pass: 30 % of them at 2 g still leave the median at g.
    body = "".join(f"{100 + k * 0.005:.6f} 0 0 0 0 {-G * (2.0 if k % 10 < 3 else 1.0):.6f} 0\n" for k in range(20))
    _write_imu(tmp_path / "seq", body)
    assert TUMSequence(tmp_path / "seq").imu is not None


@pytest.mark.parametrize(
    "body, line, match",
    [
        ("100.0 0 0 0 0 0 9.81\n100.01 0 0 0 0 9.81\n", 5, "expected 7 values 'timestamp gx gy gz ax ay az', got 6"),
        ("100.0 0 0 0 0 0 9.81\n100.01 0 0 x 0 0 9.81\n", 5, "not a number"),
        ("100.0 0 0 0 0 0 9.81\n100.01 0 0 0 nan 0 9.81\n", 5, "NaN or infinite IMU value"),
        ("100.0 0 0 0 0 0 9.81\n100.01 0 inf 0 0 0 9.81\n", 5, "NaN or infinite IMU value"),
        ("100.0 0 0 0 0 0 9.81\n100.0 0 0 0 0 0 9.81\n", 5, "duplicate timestamp"),
        ("100.01 0 0 0 0 0 9.81\n100.0 0 0 0 0 0 9.81\n", 5, "decreasing timestamp"),
        ("100.0 0 0 0 0 0 9.81\nnan 0 0 0 0 0 9.81\n", 5, "timestamp is NaN or infinite"),
    ],
)
def test_bad_imu_file_names_the_line(tmp_path, body, line, match):
    _write_seq(tmp_path / "seq", _times(2))
    _write_imu(tmp_path / "seq", body)
    with pytest.raises(DataFormatError, match=re.escape(f"imu.txt:{line}: {match}")):
        TUMSequence(tmp_path / "seq")


def test_imu_file_without_samples(tmp_path):
    _write_seq(tmp_path / "seq", _times(2))
    _write_imu(tmp_path / "seq", "# nothing else\n")
    with pytest.raises(DataFormatError, match=r"imu\.txt: no IMU samples"):
        TUMSequence(tmp_path / "seq")
    (tmp_path / "seq" / "imu.txt").unlink()
    seq = TUMSequence(tmp_path / "seq")
    assert seq.imu is None and seq.attitude is None


def test_synth_folder_imu_reads_back_as_the_in_memory_stream(tmp_path):
    from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
    from torchslam.imu import attitude_errors

    mem = generate_sequence(SyntheticConfig(frames=20, width=64, height=48, trajectory="handheld"))
    tum = TUMSequence(write_tum_folder(mem, tmp_path / "synth"))
    assert torch.allclose(tum.imu.timestamps, mem.imu.timestamps, atol=1e-6)
    assert torch.allclose(tum.imu.gyro, mem.imu.gyro, atol=1e-8) and torch.allclose(tum.imu.accel, mem.imu.accel, atol=1e-8)
    R_mem, ok_mem = mem.attitude.at(mem.timestamps)
    R_tum, ok_tum = tum.attitude.at(tum.timestamps)
    assert bool(ok_mem.all()) and bool(ok_tum.all())
    # Same filter, start and samples; the files round stamps to 1 us and values to 1e-9.
    assert (R_tum - R_mem).abs().max() < 1e-5
    # Frame convention and gravity sign: the stream follows the true attitude (a flipped gravity
    # or a body frame other than the camera's would be tens of degrees off).
    tilt, yaw = attitude_errors(R_tum, mem.groundtruth.T_wc[:, :3, :3])
    assert float(tilt.abs().max()) < math.radians(0.5) and float(yaw.abs().max()) < math.radians(0.5)


def test_pinned_frames_need_cuda(shared_data):
    import torch

    from torchslam.errors import ConfigError

    if torch.cuda.is_available():
        seq = TUMSequence(shared_data / "tum_fr1_xyz", end=2, pin_memory=True)
        assert seq[0].rgb.is_pinned() and seq[0].depth.is_pinned()
        torch.testing.assert_close(seq[0].rgb, TUMSequence(shared_data / "tum_fr1_xyz", end=2)[0].rgb, atol=0, rtol=0)
    else:
        with pytest.raises(ConfigError, match="pin_memory"):
            TUMSequence(shared_data / "tum_fr1_xyz", end=2, pin_memory=True)
    with pytest.raises(ConfigError, match="pin_memory"):
        TUMSequence(shared_data / "tum_fr1_xyz", end=2, pin_memory="yes")
