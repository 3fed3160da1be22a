"""``torchslam run --params CKPT`` and ``scripts/train.py``."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch
import yaml

from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.errors import ConfigError
from torchslam.learn import PairWeightNet, learnable, load_checkpoint, save_checkpoint
from torchslam.systems.nislam import NISlamConfig
from torchslam.app.run import resolve_config

from tests._helpers import load_script

SMALL = ["--set", "data.synthetic.frames=6", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120",
         "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100"]


def _checkpoint(path, sigma=0.37, lam=0.023, temperature=0.007):
    p = learnable(NISlamConfig(), ["kcc.sigma", "kcc.lam", "kcc.temperature"])
    with torch.no_grad():
        p.raw["kcc__sigma"].fill_(math.log(sigma))
        p.raw["kcc__lam"].fill_(math.log(lam))
        p.raw["kcc__temperature"].fill_(math.log(temperature))
    return save_checkpoint(path, p, {"what": "kcc"})


def test_run_applies_checkpoint_values_and_records_them(tmp_path, capsys):
    ckpt = _checkpoint(tmp_path / "params.pt")
    out = tmp_path / "run"
    rc = main(["run", "--data", "synthetic", "--out", str(out), "--no-progress", "--no-tensorboard",
               "--params", str(ckpt), *SMALL])
    assert rc == 0, capsys.readouterr().err
    resolved = yaml.safe_load((out / "config.yaml").read_text())
    assert resolved["kcc"]["sigma"] == pytest.approx(0.37, rel=1e-12)
    assert resolved["kcc"]["lam"] == pytest.approx(0.023, rel=1e-12)
    assert resolved["kcc"]["temperature"] == pytest.approx(0.007, rel=1e-12)
    assert resolved["kcc"]["ortho_height"] == 90  # --set values stay
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["params"] == str(ckpt)
    # the saved config rebuilds the same system config
    cfg = config_from_dict(NISlamConfig, {k: v for k, v in resolved.items() if k not in ("system", "data", "device")})
    assert cfg.kcc.sigma == pytest.approx(0.37, rel=1e-12)


def test_params_sit_between_config_file_and_set(tmp_path):
    ckpt = _checkpoint(tmp_path / "params.pt")
    cfg_file = tmp_path / "c.yaml"
    cfg_file.write_text("kcc:\n  sigma: 0.9\n  T_K: 40.0\n")
    system, _, _ = resolve_config("nislam", cfg_file, [], params=ckpt)
    assert system.kcc.sigma == pytest.approx(0.37) and system.kcc.T_K == 40.0  # file's other kcc keys kept
    system, _, _ = resolve_config("nislam", cfg_file, ["kcc.sigma=0.5"], params=ckpt)
    assert system.kcc.sigma == 0.5 and system.kcc.lam == pytest.approx(0.023) and system.kcc.T_K == 40.0
    # a --set in one section keeps the file's other keys of that section
    system, _, _ = resolve_config("nislam", cfg_file, ["kcc.lam=0.2"])
    assert (system.kcc.sigma, system.kcc.lam, system.kcc.T_K) == (0.9, 0.2, 40.0)


def test_run_rejects_bad_checkpoints_naming_file_and_key(tmp_path, capsys):
    good = _checkpoint(tmp_path / "nislam.pt")
    net = save_checkpoint(tmp_path / "net.pt", PairWeightNet())
    doc = load_checkpoint(good)
    doc["values"]["kcc.nonsense"] = 1.0
    unknown = tmp_path / "unknown.pt"
    torch.save(doc, unknown)
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    unsafe = tmp_path / "unsafe.pt"
    torch.save({**doc, "extra": {"args": argparse.Namespace(lr=0.1)}}, unsafe)
    cases = [
        (["--params", str(good), "--system", "gcslam"], [str(good), "NISlamConfig", "gcslam"]),
        (["--params", str(net)], [str(net), "PairWeightNet"]),
        (["--params", str(unknown)], [str(unknown), "kcc.nonsense", "unknown key"]),
        (["--params", str(junk)], [str(junk), "not a readable"]),
        (["--params", str(unsafe)], [str(unsafe), "unsafe pickle that would import argparse.Namespace"]),
        (["--params", str(tmp_path / "missing.pt")], ["missing.pt", "no such checkpoint"]),
    ]
    for args, needles in cases:
        out = tmp_path / "never"
        rc = main(["run", "--data", "synthetic", "--out", str(out), "--no-progress", *args, *SMALL])
        err = capsys.readouterr().err
        assert rc == 2, args
        for needle in needles:
            assert needle in err, (needle, err)
        if args[1] == str(unsafe):  # one line, not PyTorch's advice to load it with weights_only=False
            assert len(err.strip().splitlines()) == 1 and "weights_only" not in err, err
        assert not out.exists()
    with pytest.raises(ConfigError, match="kcc.nonsense"):
        resolve_config("nislam", None, [], params=unknown)


def test_train_script_pairnet_writes_checkpoint_metrics_and_events(tmp_path, capsys):
    script = load_script("train")
    out = tmp_path / "pairnet"
    rc = script.main(["--what", "pairnet", "--out", str(out), "--steps", "3", "--train-seeds", "0-1", "--val-seeds", "100"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "validation (unit weights -> net)" in printed and "checkpoint:" in printed
    doc = load_checkpoint(out / "params.pt")
    assert doc["kind"] == "module" and doc["extra"]["what"] == "pairnet"
    net = PairWeightNet(**doc["extra"]["architecture"])
    net.load_state_dict(doc["state_dict"])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train_config"]["train_seeds"] == [0, 1] and metrics["val_graphs"] == 1
    assert list(out.glob("events.out.tfevents.*"))


def test_train_script_kcc_checkpoint_runs(tmp_path, capsys):
    script = load_script("train")
    out = tmp_path / "kcc"
    rc = script.main(["--what", "kcc", "--out", str(out), "--steps", "2", "--train-seeds", "0", "--val-seeds", "100"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "values (default -> learned)" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["default"]["sigma"] == 0.2 and metrics["learned"]["sigma"] != 0.2
    system, _, _ = resolve_config("nislam", None, [], params=out / "params.pt")
    assert system.kcc.sigma == pytest.approx(metrics["learned"]["sigma"], rel=1e-12)
    with pytest.raises(SystemExit):
        script.main(["--what", "pairnet", "--out", str(out), "--tum", "x"])
