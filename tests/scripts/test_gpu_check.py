"""``scripts/gpu_check.py`` in its CPU quick mode: every part runs, agrees and is written out."""

from __future__ import annotations

import json

import pytest
import torch

from tests._helpers import load_script


def test_quick_cpu_check_runs_every_part(tmp_path):
    gpu_check = load_script("gpu_check")
    assert gpu_check.main(["--device", "cpu", "--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "gpu_check.json").read_text())
    assert result["errors"] == {}
    checks = {r["check"] for r in result["agreement"]}
    assert any(c.startswith("nislam on synthetic") for c in checks) and any(c.startswith("gcslam-dense") for c in checks)
    assert any(c.startswith("FastGO") for c in checks) and any(c.startswith("pose graph") for c in checks)
    assert any(c.startswith("lockstep NI-SLAM") for c in checks)
    assert all(r["ok"] for r in result["agreement"])
    assert len(result["timings"]) == 6 and all(r["value"] > 0 for r in result["timings"])
    assert "| agreement check |" in (tmp_path / "gpu_check.md").read_text()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_cuda_without_a_gpu_says_so(tmp_path, capsys):
    gpu_check = load_script("gpu_check")
    assert gpu_check.main(["--out", str(tmp_path)]) == 2
    assert "no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "gpu_check.json").exists()
