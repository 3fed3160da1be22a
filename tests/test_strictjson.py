"""Strict JSON: no Infinity/NaN token in anything torchslam writes or prints."""

import json
import math

import numpy as np
import pytest
import torch

from torchslam.strictjson import dumps, sanitize


def _strict_loads(text: str):
    def refuse(token):
        raise AssertionError(f"non-strict JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_values_become_null_with_the_reason():
    doc = {"a": math.inf, "b": [1.0, -math.inf, {"c": math.nan}], "t": torch.tensor([1.0, math.nan]),
           "n": np.float64("inf"), "ok": 2.5, "flag": True, "none": None}
    out = _strict_loads(dumps(doc))
    assert out["a"] is None and out["b"] == [1.0, None, {"c": None}] and out["t"] == [1.0, None]
    assert out["n"] is None and out["ok"] == 2.5 and out["flag"] is True and out["none"] is None
    assert out["non_finite"] == {"a": "inf", "b[1]": "-inf", "b[2].c": "nan", "t[1]": "nan", "n": "inf"}
    # A finite document is unchanged, with no note.
    assert _strict_loads(dumps({"x": [1, 2.0, "s"]})) == {"x": [1, 2.0, "s"]}
    clean, replaced = sanitize([math.inf])
    assert clean == [None] and replaced == {"[0]": "inf"}
    with pytest.raises(TypeError, match="not JSON serialisable: object at x"):
        dumps({"x": object()})


def test_calibrate_time_json_is_strict(monkeypatch, capsys):
    from torchslam import cli
    from torchslam.app import calibrate_time as time_offset

    class Estimate:
        def to_dict(self):
            return {"offset_s": 0.0, "costs": [math.inf] * 67 + [0.5]}

    monkeypatch.setattr(time_offset, "estimate_attitude_time_offset", lambda *a, **k: Estimate())
    assert cli.main(["calibrate-time", "--json", "--pairs", "2"]) == 0
    out = _strict_loads(capsys.readouterr().out)
    assert out["costs"][:67] == [None] * 67 and out["costs"][67] == 0.5
    assert len(out["non_finite"]) == 67 and out["non_finite"]["costs[0]"] == "inf"


def _synth_with_absurd_groundtruth(tmp_path):
    from torchslam.cli import main

    data = tmp_path / "seq"
    assert main(["synth", "--out", str(data), "--frames", "10", "--width", "160", "--height", "120"]) == 0
    lines = (data / "groundtruth.txt").read_text().splitlines()
    row = next(i for i, line in enumerate(lines) if line and not line.startswith("#")) + 4
    parts = lines[row].split()
    parts[1] = "1e300"
    lines[row] = " ".join(parts)
    (data / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return data


def test_groundtruth_of_1e300_is_a_failed_evaluation_in_strict_json(tmp_path, capsys):
    from torchslam.cli import main

    data = _synth_with_absurd_groundtruth(tmp_path)
    capsys.readouterr()
    out = tmp_path / "run"
    assert main(["run", "--data", str(data), "--out", str(out), "--no-progress", "--set", "attitude=groundtruth"]) == 1
    line = capsys.readouterr().out
    assert "ATE RMSE evaluation failed (non-finite ATE" in line
    m = _strict_loads((out / "metrics.json").read_text())
    assert m["groundtruth"] is True and m["ate_rmse_m"] is None and m["ate_error"].startswith("non-finite")
    # The batch summary shows the row as failed, and summary.json is strict too.
    batch = tmp_path / "batch"
    assert main(["batch", str(data), "--out", str(batch), "--set", "attitude=groundtruth", "--no-tensorboard"]) == 1
    doc = _strict_loads((batch / "summary.json").read_text())
    (row,) = doc["rows"]
    assert row["status"] == "failed" and row["message"].startswith("evaluation failed: non-finite ATE")
    assert doc["totals"]["ok"] == 0 and doc["totals"]["failed"] == 1
    assert "| failed |" in (batch / "summary.md").read_text()
    # A rerun finds the complete folder and still does not call it ok.
    capsys.readouterr()
    assert main(["batch", str(data), "--out", str(batch), "--set", "attitude=groundtruth", "--no-tensorboard"]) == 1
    assert _strict_loads((batch / "summary.json").read_text())["rows"][0]["status"] == "failed"
