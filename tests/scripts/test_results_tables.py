"""scripts/results_tables.py: the README's Results tables come from the stored result files."""

import json
import shutil
import sys
from pathlib import Path

import pytest

from tests._helpers import REPO_ROOT, load_script

rt = load_script("results_tables")
STORED = REPO_ROOT / "scripts" / "results" / "defaults_2026-12-07"


def test_the_readme_shows_the_stored_results_tables():
    readme = (REPO_ROOT / "README.md").read_text()
    found = rt.tables(STORED)
    assert set(found) == {"nislam", "loops", "gcslam", "stages", "speed", "cpu"}
    for name, table in found.items():
        for line in table.splitlines():
            assert line in readme, f"{name}: the README lacks {line!r}"


def test_names_and_grouping():
    assert rt.display("tum_fr1_xyz-there-and-back") == "fr1/xyz there and back"
    assert rt.display("7scenes_redkitchen/8") == "7-Scenes /8"
    assert rt.display("other_seq") == "other_seq"
    assert rt._synthetic_seed("synthetic-loop-103") == "103" and rt._synthetic_seed("tum_fr1_xyz") is None
    run = lambda ate: {"default": {"ate_cm": ate}}
    result = {"settings": ["default"], "frontends": ["sparse"], "rows": [
        {"name": "synthetic-orbit-2", "split": "tuning", "runs": {"sparse": run(0.1)}},
        {"name": "a/4", "split": "tuning", "runs": {"sparse": run(2.0)}},
        {"name": "a", "split": "tuning", "runs": {"sparse": run(1.0)}},
        {"name": "a/6", "split": "tuning", "runs": {"sparse": run(3.0)}},
        {"name": "b", "split": "held-out", "runs": {"sparse": run(0.5)}},
        {"name": "synthetic-orbit-7", "split": "tuning", "runs": {"sparse": run(0.2)}},
    ]}
    # Real sequences before synthetic ones in each split, strides of one sequence in one row.
    assert rt.gcslam_table(result).splitlines()[2:] == [
        "| tuning | a /4 | 2.00 |", "| tuning | a | 1.00 |", "| tuning | a /6 | 3.00 |",
        "| tuning | synthetic 2 / 7 | 0.10 / 0.20 |", "| held out | b | 0.50 |"]


def test_loops_that_differ_by_attitude_are_shown_apart():
    def run(att, accepted, kinds):
        return {"rule": "chi2", "seed": 100, "depth_noise": True, "attitude": att, "ate_rmse_m": 0.005,
                "loops_accepted": accepted, "loops_verified": 2,
                "planted_accepted_by_kind": dict(zip(("elsewhere", "offset 1 m", "offset 0.3 m"), kinds))}
    table = rt.loops_table([{"long": [run("groundtruth", 2, (0, 0, 2)), run("simulated", 1, (0, 1, 2))]}])
    assert table.splitlines()[2] == "| 100 (held out) | on | 0.50 | 0.50 | 1 / 2; 2 / 2 | 0 / 0 / 2; 0 / 1 / 2 |"


def test_a_missing_file_leaves_its_table_out(tmp_path, monkeypatch, capsys):
    shutil.copy(STORED / "bench_gcslam.json", tmp_path)
    assert set(rt.tables(tmp_path)) == {"gcslam"}
    monkeypatch.setattr(sys, "argv", ["results_tables.py", str(tmp_path)])
    rt.main()
    out = capsys.readouterr().out
    assert "<!-- gcslam -->" in out and f"<!-- nislam: no result file in {tmp_path} -->" in out


def test_a_folder_that_does_not_exist_is_an_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["results_tables.py", str(tmp_path / "nowhere")])
    with pytest.raises(SystemExit) as exc:
        rt.main()
    assert exc.value.code == 2 and "nowhere: no such folder" in capsys.readouterr().err


def test_the_stored_speed_rows_are_medians_of_both_checkouts():
    idle = json.loads((STORED / "bench_checkouts_idle.json").read_text())
    row = idle["rows"][0]
    runs = row["fps"]["other"] + row["fps"]["this"]
    assert len(runs) == 6
    line = rt.speed_table(idle, {"rows": []}).splitlines()[2]
    assert line.startswith(f"| NI-SLAM | fr1/xyz | {sorted(runs)[2] / 2 + sorted(runs)[3] / 2:.1f} (")
    assert line.endswith("| – | " + f"{row['ratio']:.2f} / – |")


def test_run_calls_existing_scripts_with_flags_they_take(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(rt.subprocess, "run", lambda cmd, check: calls.append(cmd))
    rt.run_all(tmp_path / "out")
    assert len(calls) == 7 + len(rt.CPU_RUNS) and (tmp_path / "out").is_dir()
    for cmd in calls:
        script = Path(cmd[1])
        assert script.parent == REPO_ROOT / "scripts" and script.exists(), cmd
        # Each flag is one of the script's own argparse options (declared as a string literal).
        source = script.read_text()
        flags = [a for a in cmd[2:] if a.startswith("--")]
        assert flags and all(f'"{f}"' in source for f in flags), (script.name, [f for f in flags if f'"{f}"' not in source])
        outs = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--out"]
        assert outs and all(o.startswith(str(tmp_path / "out")) for o in outs)


def test_cpu_table_groups_threads_and_marks_what_a_run_lacks():
    def result(med, total, wall):
        return {"median_ms_per_frame": med, "total_ms_per_frame": total, "median_wall_ms_per_frame": wall}
    ni = result({"main (tracking)": 20.0, "tslam-prepare": 5.04, "tslam-decode": 3.0, "python": 0.5}, 28.54, 21.0)
    gc = result({"main (tracking)": 10.0, "tslam-ahead": 4.0, "tslam-decode": 2.0, "tslam-optimizer": 6.0,
                 "tslam-opt-inbox": 0.2}, 22.2, 12.0)
    lines = rt.cpu_table([("A", "prep", ni), ("B", "ORB", gc)]).splitlines()
    # "all" is the runs' own total (helper threads included), not the columns' sum.
    assert lines[2] == "| A | 20.0 | 5.0 (prep) | 3.0 | – | 28.5 | 21.0 |"
    assert lines[3] == "| B | 10.0 | 4.0 (ORB) | 2.0 | 6.0 | 22.2 | 12.0 |"
