"""The run folder that `torchslam run` writes, Ctrl-C handling and run-level errors."""

import json

import pytest

import yaml

from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.data import read_tum_trajectory
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.systems import run_sequence
from torchslam.systems.nislam import NISlam, NISlamConfig
from torchslam.app.outputs import METRIC_KEYS, write_run

from tests._helpers import EditedSequence, interrupt_at

SMALL = ["--set", "data.synthetic.frames=12", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120"]



def test_run_writes_the_complete_run_folder(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["run", "--system", "nislam", "--data", "synthetic", "--out", str(out), "--no-progress",
               "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100", *SMALL])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "ATE RMSE" in printed and "frames/s" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    for key in METRIC_KEYS:
        assert key in metrics, key
    assert metrics["system"] == "nislam" and metrics["frames"] == 12
    assert metrics["attitude_source"] == "imu" and metrics["ate_rmse_m"] is not None
    traj = read_tum_trajectory(out / "trajectory.txt")
    assert len(traj) == metrics["tracked_frames"] == 12
    assert len(read_tum_trajectory(out / "keyframes.txt")) == metrics["keyframes"] >= 1
    assert (out / "map.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    resolved = yaml.safe_load((out / "config.yaml").read_text())
    assert resolved["system"] == "nislam" and resolved["kcc"]["ortho_height"] == 90
    assert resolved["data"]["synthetic"]["frames"] == 12
    assert list(out.glob("events.out.tfevents.*")), "tensorboard events missing"


def test_ctrl_c_keeps_what_was_computed(tmp_path):
    seq = generate_sequence(SyntheticConfig(frames=10, width=160, height=120, trajectory="translate"))

    cfg = config_from_dict(NISlamConfig, {"min_valid_points": 100, "kcc": {"ortho_height": 90, "ortho_width": 120}})
    seq_i = EditedSequence(seq, interrupt_at(6))
    result = run_sequence(NISlam(cfg), seq_i)
    assert result.interrupted and result.frames_processed == 6
    metrics = write_run(tmp_path, "nislam", result, seq_i)
    assert metrics["interrupted"] is True and metrics["tracked_frames"] == 6
    assert len(read_tum_trajectory(tmp_path / "trajectory.txt")) == 6


def shared_data_or_skip():
    from tests._helpers import data_root

    root = data_root() / "tum_fr1_xyz"
    if not (root / "rgb.txt").is_file():
        pytest.skip(f"real RGB-D data not found at {root}")
    return root


def test_run_errors_name_the_argument(tmp_path, capsys):
    assert main(["run", "--data", "synthetic", "--out", str(tmp_path / "a"), "--set", "kcc.sigmaa=1"]) == 2
    assert "kcc.sigmaa: unknown key" in capsys.readouterr().err
    assert main(["run", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "b")]) == 2
    assert "missing" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("kcc: [1, 2\n")
    assert main(["run", "--config", str(bad), "--out", str(tmp_path / "c")]) == 2
    assert "bad.yaml:" in capsys.readouterr().err
    # A run that fails before its first frame leaves no half-made run folder.
    assert main(["run", "--data", str(shared_data_or_skip()), "--out", str(tmp_path / "d"), "--set", "attitude=imu"]) == 2
    assert "no IMU stream" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


SMALL_NISLAM = ["--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100", *SMALL]


def _run(out, *extra):
    return main(["run", "--data", "synthetic", "--out", str(out), "--no-progress", *SMALL_NISLAM, *extra])


@pytest.fixture
def no_data_read(monkeypatch):
    """Fail the test if the run opens its sequence (the output folder is checked before that)."""
    from torchslam.app import run as run_mod

    def refuse(*args, **kwargs):
        raise AssertionError("the sequence was opened although --out cannot take the run")

    monkeypatch.setattr(run_mod, "load_sequence", refuse)


def _immutable(folder):
    """Make ``folder`` immutable (chattr +i, which stops root too) or skip."""
    import shutil
    import subprocess

    if shutil.which("chattr") is None:
        pytest.skip("chattr not available")
    folder.mkdir()
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("this file system does not support the immutable attribute")
    return folder


@pytest.mark.parametrize("case", ["file", "under-a-file", "read-only", "immutable"])
def test_an_out_that_cannot_take_a_run_is_refused_before_any_data_is_read(tmp_path, capsys, monkeypatch, no_data_read, case):
    import errno
    import os
    import subprocess

    from torchslam.app import runfolder

    if case == "file":
        out = tmp_path / "taken"
        out.write_text("x")
        expected = "exists and is not a folder"
    elif case == "under-a-file":
        (tmp_path / "plain").write_text("x")
        out = tmp_path / "plain" / "run"
        expected = "is a file, not a folder"
    elif case == "read-only":
        # Root ignores permission bits, so a read-only mount is simulated at the probe's os.open.
        out = tmp_path / "ro"
        out.mkdir()
        real_open = os.open

        def read_only(path, flags, *args):
            if str(path).startswith(str(out)) and flags & os.O_CREAT:
                raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
            return real_open(path, flags, *args)

        monkeypatch.setattr(runfolder.os, "open", read_only)
        expected = "Read-only file system"
    else:
        out = _immutable(tmp_path / "frozen")
        expected = "Operation not permitted"
    try:
        assert _run(out) == 2
    finally:
        if case == "immutable":
            subprocess.run(["chattr", "-i", str(out)], check=True)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and expected in err[0], err
    assert "Traceback" not in "".join(err)


def test_a_non_empty_out_is_refused_unless_overwrite_which_clears_it(tmp_path, capsys):
    out = tmp_path / "run"
    assert _run(out) == 0  # with TensorBoard events
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    assert any(n.startswith("events.out.tfevents.") for n in first)
    capsys.readouterr()
    assert _run(out, "--no-tensorboard", "--set", "kcc.sigma=0.3") == 2
    err = capsys.readouterr().err
    assert str(out) in err and "not empty" in err and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first  # untouched
    assert _run(out, "--no-tensorboard", "--set", "kcc.sigma=0.3", "--overwrite") == 0
    names = {p.name for p in out.iterdir()}
    assert not any(n.startswith("events.out.tfevents.") for n in names)  # the old run's events are gone
    assert yaml.safe_load((out / "config.yaml").read_text())["kcc"]["sigma"] == 0.3
    # --overwrite never clears a folder holding files a run does not write.
    (out / "notes.md").write_text("mine")
    capsys.readouterr()
    assert _run(out, "--overwrite") == 2
    err = capsys.readouterr().err
    assert "'notes.md'" in err and "--overwrite refused" in err
    assert (out / "notes.md").read_text() == "mine" and (out / "metrics.json").is_file()


def test_the_default_out_folder_is_always_a_new_one(tmp_path):
    from torchslam.app.run import default_out_dir

    first = default_out_dir("nislam", "synthetic", root=tmp_path)
    assert first.name.startswith("nislam-synthetic-") and not first.exists()
    first.mkdir()
    second = default_out_dir("nislam", "synthetic", root=tmp_path)
    assert second != first and not second.exists() and second.name.startswith(first.name)


@pytest.mark.parametrize("failing", ["map.ply", "trajectory.txt"])
def test_a_write_error_at_the_end_keeps_the_other_files_and_says_so(tmp_path, capsys, monkeypatch, failing):
    import errno
    import os

    from torchslam.app import outputs

    def full_disk(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    if failing == "map.ply":
        monkeypatch.setattr(outputs, "write_ply", full_disk)
    else:
        real = outputs.write_tum_trajectory
        monkeypatch.setattr(outputs, "write_tum_trajectory",
                            lambda path, *a, **k: full_disk(path) if path.name == failing else real(path, *a, **k))
    out = tmp_path / "run"
    assert _run(out, "--no-tensorboard") == 1
    captured = capsys.readouterr()
    err = [ln for ln in captured.err.splitlines() if ln.startswith("torchslam run:")]
    assert len(err) == 1 and "Traceback" not in captured.err
    assert str(out / failing) in err[0] and "No space left on device" in err[0] and "kept" in err[0]
    assert not (out / failing).exists()
    kept = {"trajectory.txt", "keyframes.txt", "map.ply", "metrics.json", "config.yaml"} - {failing}
    assert kept <= {p.name for p in out.iterdir()}
    for name in kept:
        assert name in err[0]
    assert json.loads((out / "metrics.json").read_text())["frames"] == 12


def test_an_interrupted_run_writes_the_partial_run_and_exits_130(tmp_path, capsys, monkeypatch):
    from torchslam.app import run as run_mod

    real = run_mod.load_sequence
    monkeypatch.setattr(run_mod, "load_sequence", lambda data, cfg, device="cpu": EditedSequence(real(data, cfg, device), interrupt_at(5)))
    out = tmp_path / "run"
    assert _run(out, "--no-tensorboard") == 130
    assert "interrupted" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] is True and metrics["processed_frames"] == 5
    assert len(read_tum_trajectory(out / "trajectory.txt")) == metrics["tracked_frames"] == 5


def test_an_odd_frame_of_a_real_sequence_is_skipped_and_counted(tmp_path, capsys):
    import cv2
    import numpy as np

    from tests._helpers import copy_tum_frames

    from torchslam.data import TUMSequence

    seq = copy_tum_frames(shared_data_or_skip(), tmp_path / "tum_fr1_xyz", 9)  # the name selects the fr1 preset
    frames = TUMSequence(seq)
    depth, rgb = frames.depth_paths[3], frames.rgb_paths[5]
    cv2.imwrite(str(depth), (cv2.imread(str(depth), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))  # 8-bit depth
    cv2.imwrite(str(rgb), cv2.resize(cv2.imread(str(rgb)), (320, 240)))  # a resized colour image
    out = tmp_path / "run"
    assert main(["run", "--data", str(seq), "--out", str(out), "--no-progress", "--no-tensorboard"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    n = len(frames)
    assert metrics["frames"] == n and metrics["processed_frames"] == n - 2 and metrics["skipped_frames"] == 2
    assert [s["index"] for s in metrics["skipped"]] == [3, 5]
    assert str(depth) in metrics["skipped"][0]["reason"] and "16-bit" in metrics["skipped"][0]["reason"]
    assert str(rgb) in metrics["skipped"][1]["reason"] and "320x240" in metrics["skipped"][1]["reason"]
    assert len(read_tum_trajectory(out / "trajectory.txt")) == metrics["tracked_frames"]
    assert metrics["ate_rmse_m"] is not None


def test_a_synth_folder_runs_on_its_own_imu_as_the_in_memory_sequence_does(tmp_path, capsys):
    from torchslam.data import TUMSequence
    from torchslam.eval import ate
    from torchslam.systems.nislam import attitude_stream

    n, size, traj = 30, ["160", "120"], "handheld"
    folder = tmp_path / "seq"
    assert main(["synth", "--out", str(folder), "--frames", str(n), "--width", size[0], "--height", size[1],
                 "--trajectory", traj]) == 0
    nislam = ["--no-progress", "--no-tensorboard", "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120",
              "--set", "min_valid_points=100", "--set", "attitude=imu"]
    assert main(["run", "--data", str(folder), "--out", str(tmp_path / "tum"), *nislam]) == 0
    assert main(["run", "--data", "synthetic", "--out", str(tmp_path / "mem"), *nislam,
                 "--set", f"data.synthetic.frames={n}", "--set", f"data.synthetic.width={size[0]}",
                 "--set", f"data.synthetic.height={size[1]}", "--set", f"data.synthetic.trajectory={traj}"]) == 0
    capsys.readouterr()
    m_tum = json.loads((tmp_path / "tum" / "metrics.json").read_text())
    m_mem = json.loads((tmp_path / "mem" / "metrics.json").read_text())
    assert m_tum["attitude_source"] == m_mem["attitude_source"] == "imu"
    assert m_tum["tracked_frames"] == m_mem["tracked_frames"] == n
    # The folder holds 8-bit colour and depth rounded to 1/5000 m: the runs agree to well under a
    # millimetre (measured: 0.05 mm at most), in the same world frame.
    est_tum = read_tum_trajectory(tmp_path / "tum" / "trajectory.txt")
    est_mem = read_tum_trajectory(tmp_path / "mem" / "trajectory.txt")
    assert ate(est_tum, est_mem, align="none").stats["max"] < 5e-4
    assert m_tum["ate_rmse_m"] == pytest.approx(m_mem["ate_rmse_m"], abs=2e-4)
    # The default ('auto') takes the folder's IMU too, not a gyro simulated from the ground truth.
    assert attitude_stream(TUMSequence(folder), NISlamConfig()).source == "imu"
