"""scripts/bench_startup.py: the instants from a fresh interpreter to a run's first frame."""

import json
import sys
from pathlib import Path

import pytest

from tests._helpers import load_script
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder

startup = load_script("bench_startup")
REPO = Path(__file__).resolve().parents[2]


def test_measures_each_checkout_in_its_own_process_and_writes_the_medians(tmp_path, monkeypatch):
    write_tum_folder(generate_sequence(SyntheticConfig(frames=6, width=80, height=60)), tmp_path / "data" / "seq")
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "data"))
    out = tmp_path / "startup.json"
    monkeypatch.setattr(sys, "argv", ["bench_startup.py", "--other", str(REPO), "--systems", "nislam",
                                      "--sequences", "seq", "--rounds", "1", "--frames", "2", "--out", str(out)])
    startup.main()
    row = json.loads(out.read_text())["rows"][0]
    assert (row["system"], row["sequence"], row["rounds"]) == ("nislam", "seq", 1)
    for label in ("other", "this"):
        m = row[label]
        assert 0 < m["start_called_s"] <= m["start_returned_s"] <= m["first_frame_s"] <= m["end_s"]
        assert m["fps_end_to_end"] > 0


def test_a_checkout_whose_torchslam_was_not_the_one_imported_is_refused(tmp_path, monkeypatch):
    # A folder without torchslam as --other: the run imports the installed one, which must not
    # be passed off as the other checkout's.
    write_tum_folder(generate_sequence(SyntheticConfig(frames=3, width=80, height=60)), tmp_path / "data" / "seq")
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "data"))
    (tmp_path / "empty").mkdir()
    monkeypatch.setattr(sys, "argv", ["bench_startup.py", "--other", str(tmp_path / "empty"), "--systems", "nislam",
                                      "--sequences", "seq", "--rounds", "1", "--frames", "2", "--out", str(tmp_path / "o.json")])
    with pytest.raises(SystemExit, match="the other run imported another torchslam, not .*empty's"):
        startup.main()
