"""scripts/bench_rolling_shutter.py end to end on a tiny planted sequence (the real sequences left out)."""

import json
import math
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_rolling_shutter.py"


def test_the_dense_front_end_runs_without_and_with_the_model_and_the_rows_are_written(tmp_path):
    out = tmp_path / "r.json"
    subprocess.run([sys.executable, str(SCRIPT), "--seeds", "100", "--frames", "24", "--size", "160x120", "--real", "",
                    "--stride", "2", "--jobs", "2", "--out", str(out)], check=True, capture_output=True, text=True)
    res = json.loads(out.read_text())
    assert res["planted_s"] == 0.03 and res["readout_s"] == 0.03 and res["size"] == [160, 120] and res["stride"] == 2
    (row,) = res["rows"]
    assert row["split"] == "held out" and row["sequence"] == "synthetic orbit seed 100"
    assert row["without"]["readout_time_s"] == 0.0 and row["without"]["moved"] == {"frames": 0, "keyframes": 0}
    assert row["with"]["readout_time_s"] == 0.03 and row["with"]["moved"]["frames"] > 0
    assert all(math.isfinite(row[k]["ate_cm"]) for k in ("without", "with", "global_shutter"))


def test_bad_arguments_are_refused_by_name(tmp_path):
    for flag, value in (("--size", "big"), ("--jobs", "0"), ("--stride", "0")):
        p = subprocess.run([sys.executable, str(SCRIPT), flag, value, "--real", "", "--out", str(tmp_path / "r.json")],
                           capture_output=True, text=True)
        assert p.returncode == 2 and f"{flag} {value}" in p.stderr
