"""scripts/bench_depth_latency.py end to end on a tiny planted sequence (fr1/xyz and the dense front-end left out)."""

import json
import math
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_depth_latency.py"


def test_each_system_runs_at_zero_and_auto_and_the_rows_are_written(tmp_path):
    out = tmp_path / "r.json"
    subprocess.run([sys.executable, str(SCRIPT), "--seeds", "100", "--frames", "10", "--size", "160x120", "--no-tum",
                    "--planted", "-0.02", "--systems", "nislam,gcslam-sparse", "--out", str(out)], check=True, capture_output=True, text=True)
    res = json.loads(out.read_text())
    assert res["planted_s"] == -0.02 and res["size"] == [160, 120]
    rows = res["rows"]
    assert [r["system"] for r in rows] == ["nislam", "gcslam-sparse"]
    for r in rows:
        assert r["split"] == "held out" and r["default"]["depth_time_offset_ms"] == 0.0
        # auto estimated the latency (a 10-frame folder as one run) within the search range
        assert abs(r["auto"]["depth_time_offset_ms"]) < 80.0
        assert all(math.isfinite(r[k]["ate_cm"]) and r[k]["fps_end_to_end"] > 0 for k in ("default", "auto"))


def test_bad_arguments_are_refused_by_name(tmp_path):
    for flag, value in (("--size", "big"), ("--systems", "orbslam")):
        p = subprocess.run([sys.executable, str(SCRIPT), flag, value, "--no-tum", "--out", str(tmp_path / "r.json")],
                           capture_output=True, text=True)
        assert p.returncode == 2 and f"{flag} {value}" in p.stderr
