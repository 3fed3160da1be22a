"""scripts/bench_cpu.py: CPU per frame of a run, by the threads torchslam names."""

import json
import sys
from pathlib import Path

import pytest

from tests._helpers import load_script
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder

pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc")
bench_cpu = load_script("bench_cpu")


def test_a_run_is_split_by_its_named_threads(tmp_path, monkeypatch):
    folder = tmp_path / "seq"
    write_tum_folder(generate_sequence(SyntheticConfig(frames=4, width=80, height=60)), folder)
    out = tmp_path / "cpu.json"
    monkeypatch.setattr(sys, "argv", ["bench_cpu.py", "--sequence", str(folder), "--frames", "1,3", "--rounds", "1",
                                      "--out", str(out)])
    bench_cpu.main()
    r = json.loads(out.read_text())
    assert r["frames"] == [1, 3] and len(r["rounds"]) == 1 and len(r["wall_ms_per_frame"]) == 1
    # The tracking thread and the thread preparing frames ahead, which live through the run (the
    # loader's decoding thread may be done with four tiny frames before the first sample).
    assert {bench_cpu.MAIN, "tslam-prepare"} <= set(r["median_ms_per_frame"])
    # A thread is measured to its last sample (every 20 ms), so on runs this short the figures are
    # only the sampler's to within tens of ms; they are finite and add up to the total.
    values = r["median_ms_per_frame"].values()
    assert all(abs(v) < 1e4 for v in values) and sum(values) == pytest.approx(r["total_ms_per_frame"])


def test_bad_frame_counts_are_refused(tmp_path, monkeypatch, capsys):
    for frames in ("5,5", "0,3", "a,b"):
        monkeypatch.setattr(sys, "argv", ["bench_cpu.py", "--sequence", str(tmp_path), "--frames", frames])
        with pytest.raises(SystemExit) as exc:
            bench_cpu.main()
        assert exc.value.code == 2 and "--frames" in capsys.readouterr().err
