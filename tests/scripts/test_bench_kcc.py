"""scripts/bench_kcc.py: the front-end micro-benchmark's figures, its inputs and its command line."""

import json
import math

import pytest
import torch

from torchslam.errors import ShapeError
from torchslam.kcc import KCCConfig

from tests._helpers import load_script

bench_kcc = load_script("bench_kcc")
benchmark_frontend = bench_kcc.benchmark_frontend


def test_benchmark_runs_small_and_reports_consistent_figures():
    cfg = KCCConfig(ortho_height=36, ortho_width=48)
    out = benchmark_frontend(batch_size=2, image_size=(48, 64), cfg=cfg, repeats=3, warmup=1)
    assert out["batch_size"] == 2
    for key, value in out.items():
        assert math.isfinite(value) and value > 0, key
    assert out["total_ms_per_frame"] == pytest.approx(out["total_ms_per_batch"] / 2)
    assert out["frames_per_s"] == pytest.approx(1e3 / out["total_ms_per_frame"])
    assert out["best_total_ms_per_frame"] <= out["total_ms_per_frame"] + 1e-9


def test_benchmark_takes_given_frames_and_needs_depth_with_rgb():
    rgb = torch.rand(1, 3, 24, 32, generator=torch.Generator().manual_seed(0))
    depth = torch.full((1, 1, 24, 32), 1.5)
    cfg = KCCConfig(ortho_height=16, ortho_width=20)
    out = benchmark_frontend(cfg=cfg, repeats=1, warmup=0, rgb=rgb, depth=depth)
    assert out["batch_size"] == 1
    with pytest.raises(ShapeError, match="depth"):
        benchmark_frontend(cfg=cfg, rgb=rgb)


def test_command_line_quick_run_writes_the_figures(tmp_path, capsys):
    out = tmp_path / "kcc.json"
    assert bench_kcc.main(["--quick", "--batch", "1", "2", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert [row["batch_size"] for row in result["rows"]] == [1, 2]
    assert result["image_size"] == [48, 64] and result["ortho"] == [36, 48]
    assert "B=  2" in capsys.readouterr().out
