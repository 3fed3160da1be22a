"""The run folder that `torchslam run` writes, Ctrl-C handling and run-level errors."""

import json

import pytest

import yaml

from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.data import read_tum_trajectory
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.slam import run_sequence
from torchslam.slam.nislam import NISlam, NISlamConfig
from torchslam.slam.outputs import METRIC_KEYS, write_run

from ._sequences import EditedSequence, interrupt_at

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
    from ..conftest import data_root

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


def test_a_synth_folder_runs_on_its_own_imu_as_the_in_memory_sequence_does(tmp_path, capsys):
    from torchslam.data import TUMSequence
    from torchslam.eval import ate
    from torchslam.slam.nislam import attitude_stream

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
