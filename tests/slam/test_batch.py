"""`torchslam batch`: run folders and summary, resume, failure isolation, Ctrl-C, engines, torchrun."""

import csv
import json
import os
import subprocess
import sys

import pytest
import yaml

from torchslam.cli import main
from torchslam.data import read_tum_trajectory
from torchslam.data.synthetic import SyntheticConfig
from torchslam.app.batch import runner as batch_mod
from torchslam.app.batch import (
    SUMMARY_COLUMNS,
    TIMING_COLUMNS,
    TOTAL_TIMING_KEYS,
    BatchOptions,
    completed_run,
    expand_sources,
    loop_count,
    run_batch,
    run_group,
    select_engine,
)
from torchslam.app.run import DataConfig

from tests._helpers import REPO_ROOT, EditedSequence, interrupt_at

# Tiny synthetic sequences; NI-SLAM's orthographic map shrunk to match the 160 x 120 images.
SMALL = [
    "--set", "data.synthetic.frames=12", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120",
    "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100",
]
SMALL_OVERRIDES = tuple(SMALL[1::2])


def _batch(out, *sources, extra=()):
    return main(["batch", *sources, "--out", str(out), "--no-tensorboard", *SMALL, *extra])


def _summary(out):
    return json.loads((out / "summary.json").read_text())


def _metrics(out, name):
    return json.loads((out / name / "metrics.json").read_text())


@pytest.fixture
def count_runs(monkeypatch):
    """Count (by sequence name) the sequences the default engine actually runs."""
    names = []
    real = batch_mod.run_sequence

    def counting(system, sequence, **kw):
        names.append(sequence.name)
        return real(system, sequence, **kw)

    monkeypatch.setattr(batch_mod, "run_sequence", counting)
    return names


def test_three_synthetic_sequences_give_run_folders_and_a_summary_that_matches_them(tmp_path, capsys):
    out = tmp_path / "b"
    # TensorBoard on here: the run folder is the full one `torchslam run` writes.
    assert main(["batch", "synthetic:3", "--out", str(out), *SMALL]) == 0
    printed = capsys.readouterr().out
    doc = _summary(out)
    rows = doc["rows"]
    assert doc["system"] == "nislam" and doc["engine"] == "sequential" and doc["world_size"] == 1
    assert [r["status"] for r in rows] == ["ok"] * 3
    names = [r["name"] for r in rows]
    assert len(set(names)) == 3 and all(n in printed for n in names)
    lengths, seeds = [], set()
    for r in rows:
        folder = out / r["name"]
        for f in ("trajectory.txt", "keyframes.txt", "map.ply", "metrics.json", "config.yaml", "groundtruth.txt"):
            assert (folder / f).is_file(), (r["name"], f)
        assert list(folder.glob("events.out.tfevents.*"))
        m = _metrics(out, r["name"])
        assert r["frames"] == m["frames"] and r["processed_frames"] == m["processed_frames"]
        assert r["tracked_frames"] == m["tracked_frames"] == len(read_tum_trajectory(folder / "trajectory.txt"))
        assert r["keyframes"] == m["keyframes"] and r["loops"] == m["loops"]["accepted"]
        for key in ("ate_rmse_m", "fps_end_to_end", "fps_compute", "wall_s"):
            assert r[key] == m[key], key
        assert m["ate_rmse_m"] is not None and m["groundtruth_file"] == "groundtruth.txt"
        lengths.append(m["frames"])
        seeds.add(yaml.safe_load((folder / "config.yaml").read_text())["data"]["synthetic"]["seed"])
    assert len(set(lengths)) == 3 and max(lengths) == 12 and len(seeds) == 3
    totals = doc["totals"]
    assert totals["ok"] == 3 and totals["failed"] == 0
    assert totals["processed_frames"] == sum(lengths)
    assert totals["ate_rmse_m_mean"] == pytest.approx(sum(r["ate_rmse_m"] for r in rows) / 3, rel=1e-12)
    with open(out / "summary.csv", newline="") as fh:
        csv_rows = list(csv.DictReader(fh))
    assert [list(c) for c in csv_rows] == [list(SUMMARY_COLUMNS)] * 3
    for c, r in zip(csv_rows, rows):
        assert c["name"] == r["name"] and int(c["tracked_frames"]) == r["tracked_frames"]
        assert float(c["ate_rmse_m"]) == r["ate_rmse_m"]
    md = (out / "summary.md").read_text()
    assert all(f"| {n} | ok |" in md for n in names) and "**total** (3)" in md

    # Sequence 0 of synthetic:K is the sequence `torchslam run --data synthetic` runs.
    single = tmp_path / "single"
    assert main(["run", "--data", "synthetic", "--out", str(single), "--no-progress", "--no-tensorboard", *SMALL]) == 0
    a = read_tum_trajectory(single / "trajectory.txt")
    b = read_tum_trajectory(out / names[0] / "trajectory.txt")
    assert (a.timestamps == b.timestamps).all() and (a.T_wc - b.T_wc).abs().max() < 1e-9


def test_resume_redoes_only_the_incomplete_sequences(tmp_path, count_runs):
    out = tmp_path / "b"
    assert _batch(out, "synthetic:3") == 0
    names = [r["name"] for r in _summary(out)["rows"]]
    assert count_runs == names
    before = {n: (out / n / "metrics.json").read_bytes() for n in names}
    # Corrupt the first run's metrics; mark the second as interrupted (what Ctrl-C leaves).
    (out / names[0] / "metrics.json").write_text('{"system": "nislam", "processed')
    m1 = json.loads(before[names[1]])
    m1["interrupted"] = True
    (out / names[1] / "metrics.json").write_text(json.dumps(m1))
    count_runs.clear()
    assert _batch(out, "synthetic:3") == 0
    assert count_runs == names[:2]
    rows = _summary(out)["rows"]
    assert [r["status"] for r in rows] == ["ok", "ok", "resumed"]
    assert (out / names[2] / "metrics.json").read_bytes() == before[names[2]]
    assert rows[2]["ate_rmse_m"] == json.loads(before[names[2]])["ate_rmse_m"]
    for n in names[:2]:
        m = _metrics(out, n)
        assert m["interrupted"] is False
        assert m["ate_rmse_m"] == json.loads(before[n])["ate_rmse_m"]  # deterministic redo
    # A different request (fewer frames) would replace complete results: refused unless --overwrite.
    count_runs.clear()
    assert _batch(out, "synthetic:3", extra=["--max-frames", "5"]) == 2
    assert count_runs == []
    count_runs.clear()
    assert _batch(out, "synthetic:3", extra=["--max-frames", "5", "--overwrite"]) == 0
    assert count_runs == names and all(r["processed_frames"] == 5 for r in _summary(out)["rows"])


def test_completed_run_checks_each_part_of_the_folder(tmp_path):
    out = tmp_path / "b"
    assert _batch(out, "synthetic") == 0
    row = _summary(out)["rows"][0]
    folder = out / row["name"]
    config = yaml.safe_load((folder / "config.yaml").read_text())
    assert completed_run(folder, "nislam", "synthetic", config) is not None
    assert completed_run(folder, "gcslam", "synthetic", config) is None
    assert completed_run(folder, "nislam", "/elsewhere", config) is None
    assert completed_run(folder, "nislam", "synthetic", {**config, "sigma": 0.3}) is None
    assert completed_run(folder, "nislam", "synthetic", {**config, "device": "cuda"}) is not None
    assert completed_run(folder, "nislam", "synthetic", config, max_frames=5) is None
    lines = (folder / "trajectory.txt").read_text().splitlines()
    (folder / "trajectory.txt").write_text("\n".join(lines[:-1]) + "\n")
    assert completed_run(folder, "nislam", "synthetic", config) is None
    (folder / "trajectory.txt").write_text("\n".join(lines[:-1] + ["1 2 3"]) + "\n")
    assert completed_run(folder, "nislam", "synthetic", config) is None
    (folder / "trajectory.txt").unlink()
    assert completed_run(folder, "nislam", "synthetic", config) is None


def _tum_folder_with_broken_rgb_list(root):
    root.mkdir()
    (root / "calibration.txt").write_text("517.3 516.5 318.6 255.3 5000 640 480\n")
    (root / "rgb.txt").write_text("# colour images\n0.0 rgb/0.png\nnot-a-time rgb/1.png\n")
    (root / "depth.txt").write_text("0.0 depth/0.png\n")
    return root


def test_a_bad_source_is_a_failed_row_and_the_others_run(tmp_path, monkeypatch, capsys):
    broken = _tum_folder_with_broken_rgb_list(tmp_path / "broken")
    missing = tmp_path / "absent"
    out = tmp_path / "b"
    # A sequence whose run raises is isolated as well.
    real = batch_mod.run_sequence

    def raising(system, sequence, **kw):
        if sequence.name.startswith("synthetic-translate"):
            raise RuntimeError("tracker exploded")
        return real(system, sequence, **kw)

    monkeypatch.setattr(batch_mod, "run_sequence", raising)
    rc = _batch(out, str(broken), "synthetic:2", str(missing), str(tmp_path / "nothing-*"))
    assert rc == 1  # some sequence failed
    rows = {r["name"]: r for r in _summary(out)["rows"]}
    assert list(rows) == ["broken", "synthetic-orbit-seed0", "synthetic-translate-seed1", "absent", "nothing-"]
    assert rows["broken"]["status"] == "failed"
    assert f"{broken / 'rgb.txt'}:3" in rows["broken"]["message"]
    assert rows["absent"]["status"] == "failed" and str(missing) in rows["absent"]["message"]
    assert rows["nothing-"]["status"] == "failed" and "matches no folder" in rows["nothing-"]["message"]
    assert rows["synthetic-translate-seed1"]["status"] == "failed"
    assert rows["synthetic-translate-seed1"]["message"] == "RuntimeError: tracker exploded"
    assert "tracker exploded" in (out / "synthetic-translate-seed1" / "error.txt").read_text()
    assert rows["synthetic-orbit-seed0"]["status"] == "ok"
    assert _summary(out)["totals"]["failed"] == 4
    assert "rgb.txt:3" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["synthetic:0"], "synthetic:K"),
        (["synthetic", "--batch-size", "0"], "--batch-size"),
        (["synthetic", "--set", "kcc.sigmaa=1"], "sigmaa"),
        (["synthetic", "--max-frames", "0"], "--max-frames"),
    ],
)
def test_bad_arguments_stop_before_anything_runs(tmp_path, capsys, argv, message):
    out = tmp_path / "b"
    assert main(["batch", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_ctrl_c_keeps_finished_sequences_and_a_rerun_completes_the_batch(tmp_path, monkeypatch, count_runs):
    out = tmp_path / "b"
    real = batch_mod.run_sequence  # the counting wrapper

    def interrupt_second(system, sequence, **kw):
        return real(system, EditedSequence(sequence, interrupt_at(4)) if len(count_runs) == 1 else sequence, **kw)

    monkeypatch.setattr(batch_mod, "run_sequence", interrupt_second)
    assert _batch(out, "synthetic:3") == 130
    doc = _summary(out)
    rows = doc["rows"]
    assert doc["interrupted"] is True
    assert [r["status"] for r in rows] == ["ok", "interrupted", "not run"]
    assert rows[1]["processed_frames"] == 4 and _metrics(out, rows[1]["name"])["interrupted"] is True
    assert not (out / rows[2]["name"]).exists()
    first = (out / rows[0]["name"] / "metrics.json").read_bytes()

    monkeypatch.setattr(batch_mod, "run_sequence", real)
    count_runs.clear()
    assert _batch(out, "synthetic:3") == 0
    assert count_runs == [rows[1]["name"], rows[2]["name"]]
    assert [r["status"] for r in _summary(out)["rows"]] == ["resumed", "ok", "ok"]
    assert (out / rows[0]["name"] / "metrics.json").read_bytes() == first


def test_an_interrupt_between_groups_writes_the_summary(tmp_path):
    calls = []

    def stop_at_second_group(system, system_cfg, sequences, device, monitors, max_frames):
        calls.append(len(sequences))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return run_group(system, system_cfg, sequences, device, monitors, max_frames)

    options = BatchOptions(system="nislam", sources=("synthetic:3",), out=tmp_path / "b", batch_size=2, tensorboard=False)
    result = run_batch(options, overrides=SMALL_OVERRIDES, group_runner=stop_at_second_group)
    assert result.interrupted and calls == [2, 1]
    assert [r["status"] for r in result.rows] == ["ok", "ok", "not run"]
    assert _summary(tmp_path / "b")["rows"] == result.rows


def test_engine_dispatch_uses_lockstep_for_groups(tmp_path, monkeypatch):
    groups = []

    def run_lockstep(system_cfg, sequences, device, monitors, max_frames):
        groups.append([s.name for s in sequences])
        return run_group("nislam", system_cfg, sequences, device, monitors, max_frames)

    monkeypatch.setattr(batch_mod, "run_lockstep", run_lockstep)
    assert select_engine("nislam", 4)[0] == "lockstep"
    assert select_engine("nislam", 1)[0] == "sequential"
    assert select_engine("gcslam", 4)[0] == "lockstep"
    assert select_engine("gcslam", 1)[0] == "sequential"
    out = tmp_path / "b"
    assert _batch(out, "synthetic:3", extra=["--batch-size", "2", "--max-frames", "6"]) == 0
    doc = _summary(out)
    assert doc["engine"] == "lockstep" and doc["batch_size"] == 2
    assert groups == [[r["name"] for r in doc["rows"][:2]], [doc["rows"][2]["name"]]]
    assert [r["status"] for r in doc["rows"]] == ["ok"] * 3


def test_sources_expand_to_unique_names(tmp_path):
    for parent in ("a", "b"):
        (tmp_path / parent / "seq").mkdir(parents=True)
    (tmp_path / "a" / "notes.txt").write_text("not a folder")
    data = DataConfig(synthetic=SyntheticConfig(frames=16, seed=5, trajectory="loop"))
    src = expand_sources(
        ["synthetic:2", str(tmp_path / "a" / "*"), str(tmp_path / "b" / "seq"), str(tmp_path / "a" / "seq"), "synthetic"], data
    )
    assert [s.name for s in src] == ["synthetic-loop-seed5", "synthetic-handheld-seed6", "seq", "seq-2", "synthetic-orbit-seed7"]
    assert [s.synthetic.frames for s in src if s.synthetic] == [16, 14, 12]
    assert src[0].synthetic == SyntheticConfig(frames=16, seed=5, trajectory="loop")
    assert src[2].spec == str((tmp_path / "a" / "seq").resolve()) and src[2].source.endswith("*")
    assert [s.index for s in src] == list(range(5))


def test_loop_count_reads_each_systems_key():
    assert loop_count({"loops": {"candidates": 4, "verified": 2, "accepted": 1}}) == 1
    assert loop_count({"loops": 3}) == 3
    assert loop_count({"loop_closures": [[1, 5], [2, 9]]}) == 2
    assert loop_count({"keyframes": 3}) is None


def test_two_process_gloo_gives_the_single_process_summary(tmp_path):
    dist = pytest.importorskip("torch.distributed")
    if not dist.is_available():
        pytest.skip("this PyTorch build has no torch.distributed")
    single, multi = tmp_path / "single", tmp_path / "multi"
    assert _batch(single, "synthetic:3") == 0
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))}
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "torchslam", "batch", "synthetic:3", "--out", str(multi), "--no-tensorboard", *SMALL]
    proc = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=240, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    a, b = _summary(single), _summary(multi)
    assert b["world_size"] == 2 and len(b["rank_wall_s"]) == 2

    def strip(rows):
        return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows]

    assert strip(b["rows"]) == strip(a["rows"])
    assert {k: v for k, v in b["totals"].items() if k not in TOTAL_TIMING_KEYS} == {
        k: v for k, v in a["totals"].items() if k not in TOTAL_TIMING_KEYS
    }
    for r in a["rows"]:
        assert (multi / r["name"] / "trajectory.txt").read_text() == (single / r["name"] / "trajectory.txt").read_text()
    # Rank 1 ran the second sequence (round-robin) and said so.
    assert f"[rank 1] [1/1] {a['rows'][1]['name']}: ok" in proc.stdout


def test_a_rerun_with_another_request_is_refused_naming_the_folders_and_overwrite_redoes_them(tmp_path, capsys, count_runs):
    out = tmp_path / "b"
    assert _batch(out, "synthetic:2") == 0
    names = [r["name"] for r in _summary(out)["rows"]]
    before = {n: {p.name: p.read_bytes() for p in (out / n).iterdir()} for n in names}
    summary = (out / "summary.json").read_bytes()
    capsys.readouterr()
    count_runs.clear()
    assert _batch(out, "synthetic:2", extra=["--set", "kcc.sigma=0.3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0] and str(out) in err[0]
    assert all(f"{n} (the configuration differs: kcc.sigma)" in err[0] for n in names), err[0]
    assert count_runs == []  # nothing ran, nothing was touched
    assert {n: {p.name: p.read_bytes() for p in (out / n).iterdir()} for n in names} == before
    assert (out / "summary.json").read_bytes() == summary
    assert _batch(out, "synthetic:2", extra=["--set", "kcc.sigma=0.3", "--overwrite"]) == 0
    assert count_runs == names
    assert [r["status"] for r in _summary(out)["rows"]] == ["ok", "ok"]
    for n in names:
        assert yaml.safe_load((out / n / "config.yaml").read_text())["kcc"]["sigma"] == 0.3
    # Once redone, the same request resumes.
    count_runs.clear()
    assert _batch(out, "synthetic:2", extra=["--set", "kcc.sigma=0.3"]) == 0 and count_runs == []


def test_ctrl_c_during_an_overwrite_keeps_the_folders_it_did_not_reach(tmp_path, monkeypatch, count_runs):
    out = tmp_path / "b"
    options = BatchOptions(system="nislam", sources=("synthetic:3",), out=out, batch_size=3, tensorboard=False)
    # One group of three, run one after another: before, the whole group's folders were cleared first.
    assert not run_batch(options, overrides=SMALL_OVERRIDES, group_runner=run_group).interrupted
    names = [r["name"] for r in _summary(out)["rows"]]
    old = {n: (out / n / "metrics.json").read_bytes() for n in names}
    real = batch_mod.run_sequence

    def interrupt_second(system, sequence, **kw):
        return real(system, EditedSequence(sequence, interrupt_at(3)) if len(count_runs) == 1 else sequence, **kw)

    monkeypatch.setattr(batch_mod, "run_sequence", interrupt_second)
    count_runs.clear()
    again = BatchOptions(**{**options.__dict__, "max_frames": 8, "overwrite": True})
    result = run_batch(again, overrides=SMALL_OVERRIDES, group_runner=run_group)
    assert result.interrupted and [r["status"] for r in result.rows] == ["ok", "interrupted", "not run"]
    assert _metrics(out, names[0])["max_frames"] == 8  # the new run
    assert _metrics(out, names[1])["interrupted"] is True and _metrics(out, names[1])["processed_frames"] == 3
    assert (out / names[2] / "metrics.json").read_bytes() == old[names[2]]  # the earlier complete run, kept
    assert completed_run(out / names[2], "nislam") is not None


def test_a_second_batch_on_the_same_folder_fails_at_once_naming_the_first(tmp_path, capsys):
    out = tmp_path / "b"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", (
            "import fcntl, os, sys\n"
            "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\n"
            "os.write(fd, str(os.getpid()).encode())\n"
            "print('locked', flush=True)\n"
            "sys.stdin.read()\n"
        ), str(out / ".torchslam-batch.lock")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert _batch(out, "synthetic") == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"another torchslam batch (pid {holder.pid})" in err[0] and str(out) in err[0]
        assert sorted(p.name for p in out.iterdir()) == [".torchslam-batch.lock"]  # nothing ran
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    assert _batch(out, "synthetic") == 0  # the lock went with its process
