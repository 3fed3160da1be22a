import json
import subprocess
import sys

import pytest
import torch

from torchslam.cli import main
from torchslam.data import Trajectory, read_tum_trajectory, write_tum_trajectory
from torchslam.geometry import se3_exp


def _perturbed_copy(gt: Trajectory, seed: int = 0) -> Trajectory:
    g = torch.Generator().manual_seed(seed)
    T = se3_exp(torch.randn(6, generator=g, dtype=torch.float64))
    noise = se3_exp(0.01 * torch.randn(len(gt), 6, generator=g, dtype=torch.float64))
    return Trajectory(gt.timestamps, T @ gt.T_wc @ noise)


def test_eval_json_matches_evo(shared_data, tmp_path, capsys):
    from evo.core import metrics
    from evo.tools import file_interface

    gt_path = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    est_path = tmp_path / "est.txt"
    write_tum_trajectory(est_path, _perturbed_copy(read_tum_trajectory(gt_path)))
    assert main(["eval", "--est", str(est_path), "--gt", str(gt_path), "--json"]) == 0
    ours = json.loads(capsys.readouterr().out)
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    # The written file rounds to 1e-9 m, far below the tolerance.
    assert ours["ate_rmse_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
    assert ours["align"] == "se3" and ours["matched"] == len(ref.timestamps)


def test_eval_table_and_bad_file(shared_data, tmp_path, capsys):
    gt_path = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    assert main(["eval", "--est", str(gt_path), "--gt", str(gt_path)]) == 0
    out = capsys.readouterr().out
    assert "| ATE | se3 | 0.000000" in out
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n")
    assert main(["eval", "--est", str(bad), "--gt", str(gt_path)]) == 2
    assert f"{bad}:3: NaN or infinite value" in capsys.readouterr().err


def test_run_reports_unavailable_or_unknown_system(capsys):
    assert main(["run", "--system", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown system" in err and "available systems" in err


def test_info_prints_sequence_summary(shared_data, capsys):
    assert main(["info", str(shared_data / "tum_fr1_xyz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["rgb_list_count"] == 210 and info["depth_list_count"] == 210
    assert info["frames"] == info["associated_count"] > 190
    assert info["intrinsics_source"] == "preset:freiburg1"
    assert main(["info", str(shared_data)]) == 2  # the parent folder is not a sequence
    assert "rgb.txt" in capsys.readouterr().err


def test_python_dash_m_is_the_same_entry_point():
    proc = subprocess.run([sys.executable, "-m", "torchslam", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    for cmd in ("run", "eval", "info", "synth"):
        assert cmd in proc.stdout


def test_synth_writes_a_folder_that_info_and_run_read(tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["synth", "--out", str(out), "--frames", "4", "--width", "160", "--height", "120", "--trajectory", "translate"]) == 0
    assert "wrote 4 frames" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 4 and info["intrinsics_source"].startswith("calibration.txt")
    assert main(["synth", "--out", str(tmp_path / "x"), "--trajectory", "spiral"]) == 2
    assert "trajectory" in capsys.readouterr().err


def test_eval_help_states_every_default(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for default in ("default se3", "default 0.01, evo's --t_max_diff and the headline's", "nearest: evo's",
                    "(default, the headline's)", "(default 0)", "RPE step (default 1)", "(default frames)", "(default: table)"):
        assert default in text, default


def test_eval_by_default_reproduces_the_run_headline(shared_data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--data", str(shared_data / "tum_fr1_xyz"), "--max-frames", "15", "--out", str(out),
                 "--no-progress", "--no-tensorboard"]) == 0
    capsys.readouterr()
    m = json.loads((out / "metrics.json").read_text())
    gt = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    assert main(["eval", "--est", str(out / "trajectory.txt"), "--gt", str(gt), "--json"]) == 0
    ours = json.loads(capsys.readouterr().out)
    assert ours["ate_rmse_m"] == m["ate_rmse_m"] and ours["matched"] == m["matched"] == 15
    assert ours["ate_association"] == "nearest" and ours["ate_association_max_dt_s"] == 0.01
