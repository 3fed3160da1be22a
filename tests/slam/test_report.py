"""`torchslam report`: report.md with a table and plots from a batch folder or from run folders."""

import json

import pytest
import torch

from torchslam.cli import main
from torchslam.data import read_tum_trajectory
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import DataFormatError
from torchslam.app.report import find_groundtruth, load_batch, write_report

SMALL = [
    "--set", "data.synthetic.frames=12", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120",
    "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100",
]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path):
    return path.is_file() and path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 1000


def test_report_of_a_batch_has_table_plots_and_failures(tmp_path, capsys):
    out = tmp_path / "b"
    assert main(["batch", "synthetic:2", str(tmp_path / "absent"), "--out", str(out), "--no-tensorboard", *SMALL]) == 1
    capsys.readouterr()
    assert main(["report", str(out)]) == 0
    assert str(out / "report.md") in capsys.readouterr().out
    md = (out / "report.md").read_text()
    rows = json.loads((out / "summary.json").read_text())["rows"]
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == 2
    for r in rows:
        assert f"| {r['name']} | {r['status']} |" in md
    assert _is_png(out / "report" / "ate.png") and "(report/ate.png)" in md
    assert _is_png(out / "report" / "fps.png") and "(report/fps.png)" in md
    for r in ok:
        assert _is_png(out / "report" / f"traj-{r['name']}.png")
        # The caption's ATE is the one the run measured, so the plot used its ground truth.
        assert f"ATE RMSE {r['ate_rmse_m'] * 100:.2f} cm" in md
    assert not (out / "report" / "traj-absent.png").exists()
    assert "## Failures" in md and "absent" in md.split("## Failures")[1]


def test_report_of_plain_run_folders_rebuilds_the_synthetic_ground_truth(tmp_path):
    root = tmp_path / "runs"
    for traj in ("orbit", "translate"):
        assert main(["run", "--data", "synthetic", "--out", str(root / traj), "--no-progress", "--no-tensorboard",
                     *SMALL, "--set", f"data.synthetic.trajectory={traj}"]) == 0
    doc = load_batch(root)
    assert [r["name"] for r in doc["rows"]] == ["orbit", "translate"]
    metrics = json.loads((root / "translate" / "metrics.json").read_text())
    assert doc["rows"][1]["ate_rmse_m"] == metrics["ate_rmse_m"]
    assert "groundtruth_file" not in metrics  # written by `torchslam run`, not by a batch
    gt = find_groundtruth(root / "translate", metrics)
    truth = generate_sequence(SyntheticConfig(frames=12, width=160, height=120, trajectory="translate")).groundtruth
    assert torch.equal(gt.timestamps, truth.timestamps)
    assert (gt.T_wc - truth.T_wc).abs().max() < 1e-12
    path = write_report(root)
    assert _is_png(root / "report" / "traj-translate.png")
    assert f"ATE RMSE {metrics['ate_rmse_m'] * 100:.2f} cm" in path.read_text()


def test_ground_truth_is_found_beside_the_data(tmp_path):
    seq_dir = tmp_path / "seq"
    seq_dir.mkdir()
    (seq_dir / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    gt = find_groundtruth(tmp_path / "run", {"data": str(seq_dir)})
    assert len(gt) == 2 and gt.positions[1, 0] == 1.0
    assert find_groundtruth(tmp_path / "run", {"data": str(tmp_path / "elsewhere")}) is None
    assert len(read_tum_trajectory(seq_dir / "groundtruth.txt")) == 2


def test_report_errors_name_the_path(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == 2
    assert str(tmp_path / "nope") in capsys.readouterr().err
    (tmp_path / "summary.json").write_text("{not json")
    assert main(["report", str(tmp_path)]) == 2
    assert "summary.json" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataFormatError, match="no summary.json and no run folders"):
        load_batch(empty)


def test_report_skips_folders_that_are_not_runs_and_says_how_many(tmp_path, caplog):
    import logging

    root = tmp_path / "runs"
    assert main(["run", "--data", "synthetic", "--out", str(root / "run"), "--no-progress", "--no-tensorboard", *SMALL]) == 0
    # What scripts/train.py writes: a metrics.json of a training, not of a run.
    train = root / "train-kcc"
    train.mkdir()
    (train / "metrics.json").write_text(json.dumps({"what": "kcc", "train_config": {}, "val_ate_rmse_m": 0.01}))
    (root / "notes").mkdir()
    (root / "other").mkdir()
    (root / "other" / "metrics.json").write_text(json.dumps({"system": "orbslam", "frames": 3}))
    with caplog.at_level(logging.WARNING, logger="torchslam.app.report"):
        doc = load_batch(root)
    assert [r["name"] for r in doc["rows"]] == ["run"] and doc["rows"][0]["status"] == "ok"
    assert doc["skipped"] == ["notes", "other", "train-kcc"]
    assert "skipped 3 folder(s) that are not runs: notes, other, train-kcc" in caplog.text
    md = write_report(root).read_text()
    assert "Skipped 3 sub-folder(s) that are not runs" in md and "train-kcc" not in md.split("## Sequences")[1].split("Skipped")[0]
    # A second report does not count its own plots folder.
    assert load_batch(root)["skipped"] == ["notes", "other", "train-kcc"]
    only_training = tmp_path / "training"
    only_training.mkdir()
    (only_training / "train-kcc").mkdir()
    (only_training / "train-kcc" / "metrics.json").write_text(json.dumps({"what": "kcc"}))
    with pytest.raises(DataFormatError, match=r"no run folders with metrics.json \(1 sub-folders are not runs: train-kcc\)"):
        load_batch(only_training)
