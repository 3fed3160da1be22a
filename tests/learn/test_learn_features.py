"""Training the learned KCC channels: synthetic pairs, the objective, the loop, the script and ``run --params``."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
import yaml

from torchslam.app.run import resolve_config
from torchslam.cli import main
from torchslam.errors import ConfigError
from torchslam.kcc import KCCConfig, KCCFeatureNet, KernelCorrelator, frame_taper, load_feature_net
from torchslam.learn import (
    FeatureTrainConfig,
    evaluate_features,
    feature_loss,
    load_checkpoint,
    save_checkpoint,
    synthetic_ortho_pairs,
    train_features,
)
from torchslam.learn.features import _correlate, _reference_psr

from tests._helpers import load_script

SMALL_CFG = KCCConfig(ortho_height=60, ortho_width=80)
SMALL_PAIRS = dict(frames=16, keyframe_step=5, gaps=(3, 6), width=160, height=120)
SMALL_TRAIN = ["--set", "width=160", "--set", "height=120", "--set", "ortho_height=60", "--set", "ortho_width=80",
               "--set", "frames=16", "--set", "gaps=[3,6]", "--set", "batch_size=2", "--set", "eval_every=2"]


@pytest.fixture(scope="module")
def pairs():
    return synthetic_ortho_pairs([0, 1], SMALL_CFG, **SMALL_PAIRS)


def test_synthetic_pairs_are_a_function_of_the_seeds(pairs):
    assert len(pairs) == 2 * 3  # per seed keyframes 0, 5, 10, 15 with gaps 3, 6 cycled: 0+3, 5+6, 10+3 (15+6 > 15)
    again = synthetic_ortho_pairs([0, 1], SMALL_CFG, **SMALL_PAIRS)
    for name in ("grey", "depth", "valid"):
        assert torch.equal(getattr(pairs.keyframe, name), getattr(again.keyframe, name))
        assert torch.equal(getattr(pairs.frame, name), getattr(again.frame, name))
    other = synthetic_ortho_pairs([2], SMALL_CFG, **SMALL_PAIRS)
    assert not torch.equal(other.keyframe.grey, pairs.keyframe.grey[: len(other)])
    # the hand-crafted channels find these shifts: the ground truth and the images agree
    ev = evaluate_features(pairs, SMALL_CFG, None)
    assert ev["median_px"] < 0.5 and ev["fail_rate"] <= 0.2
    with pytest.raises(ConfigError, match="photometric"):
        synthetic_ortho_pairs([0], SMALL_CFG, photometric=1.5, **SMALL_PAIRS)
    with pytest.raises(ConfigError, match="blur_px"):
        synthetic_ortho_pairs([0], SMALL_CFG, blur_px=-1, **SMALL_PAIRS)


def test_feature_loss_reaches_every_weight_and_the_psr_term_is_zero_at_the_reference(pairs):
    torch.manual_seed(0)
    net = KCCFeatureNet(2, 4, initial_weight=0.5)
    part = pairs.select(slice(0, 4))
    ref = _reference_psr(part, SMALL_CFG)
    out = feature_loss(net, part, SMALL_CFG, ref)
    out.loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
    # the PSR term measures the distance to the reference PSR: zero against its own PSR
    with torch.no_grad():
        own = feature_loss(net, part, SMALL_CFG, out.psr.detach())
    assert float(own.psr_term) == pytest.approx(0.0, abs=1e-10)
    assert float(out.psr_term.detach()) > 0
    with pytest.raises(ConfigError, match="robust_px"):
        feature_loss(net, part, SMALL_CFG, ref, robust_px=0)


def test_training_is_reproducible_by_seed_and_picks_by_validation():
    cfg = FeatureTrainConfig(train_seeds=(0,), val_seeds=(100,), frames=16, gaps=(3, 6), width=160, height=120,
                             ortho_height=60, ortho_width=80, steps=4, batch_size=2, eval_every=2, hidden=4)
    a = train_features(cfg)
    b = train_features(cfg)
    for k, v in a.module.state_dict().items():
        assert torch.equal(v, b.module.state_dict()[k]), k
    m = a.metrics
    assert m["best_step"] in (0, 2, 4) and m["parameters"] == sum(p.numel() for p in a.module.parameters())
    scores = [h["val/score_px2"] for h in a.history if "val/score_px2" in h]
    assert m["val_learned"]["score_px2"] == pytest.approx(min(scores), rel=1e-9)
    c = train_features(FeatureTrainConfig(**{**cfg.__dict__, "seed": 1}))
    assert not torch.equal(c.module.conv1.weight, a.module.conv1.weight)
    with pytest.raises(ConfigError, match="val_seeds: must not overlap"):
        FeatureTrainConfig(train_seeds=(0, 1), val_seeds=(1,))


def test_train_script_features_checkpoint_runs_with_params(tmp_path, capsys):
    script = load_script("train")
    out = tmp_path / "features"
    rc = script.main(["--what", "features", "--out", str(out), "--steps", "2", "--train-seeds", "0", "--val-seeds", "100",
                      "--set", "hidden=4", *SMALL_TRAIN])
    assert rc == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "validation (hand-crafted -> learned)" in printed and "parameters" in printed
    doc = load_checkpoint(out / "params.pt")
    assert doc["kind"] == "module" and doc["module"] == "KCCFeatureNet" and doc["extra"]["architecture"] == {"learned": 2, "hidden": 4}
    assert load_feature_net(out / "params.pt").hidden == 4
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train_config"]["width"] == 160 and metrics["train_config"]["hidden"] == 4
    assert json.loads((out / "history.json").read_text())[0]["step"] == 0
    assert (out / "curve.png").stat().st_size > 0
    assert list(out.glob("events.out.tfevents.*"))
    # run --params selects the learned channels with this checkpoint
    system, _, _ = resolve_config("nislam", None, [], params=out / "params.pt")
    assert system.kcc.features.value == "learned" and system.kcc.features_weights == str((out / "params.pt").resolve())
    run_dir = tmp_path / "run"
    small = ["--set", "data.synthetic.frames=6", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120",
             "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100"]
    rc = main(["run", "--data", "synthetic", "--out", str(run_dir), "--no-progress", "--no-tensorboard",
               "--params", str(out / "params.pt"), *small])
    assert rc == 0, capsys.readouterr().err
    resolved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert resolved["kcc"]["features"] == "learned" and resolved["kcc"]["features_weights"].endswith("params.pt")
    assert json.loads((run_dir / "metrics.json").read_text())["tracked_frames"] == 6
    # a features checkpoint does not fit GC-SLAM, and bad --set values name the key
    with pytest.raises(ConfigError, match="KCCFeatureNet weights, which system 'gcslam'"):
        resolve_config("gcslam", None, [], params=out / "params.pt")
    assert script.main(["--what", "features", "--out", str(tmp_path / "x"), "--set", "hidden=0"]) == 2
    assert "hidden" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--what", "kcc", "--out", str(tmp_path / "y"), "--seed", "3"])


def test_module_checkpoint_of_features_is_not_config_values(tmp_path):
    from torchslam.learn import checkpoint_values
    from torchslam.systems.nislam import NISlamConfig

    ckpt = save_checkpoint(tmp_path / "f.pt", KCCFeatureNet(), {"architecture": {"learned": 2, "hidden": 8}})
    with pytest.raises(ConfigError, match="holds the weights of a KCCFeatureNet module, not config values"):
        checkpoint_values(ckpt, NISlamConfig, "nislam")


def test_training_correlates_tapered_frames_as_a_run_does(pairs):
    # ``_correlate`` (the objective and the evaluation) tapers the frame's channels by
    # ``cfg.frame_taper`` and trains the filter on untapered keyframe channels, as ``track_step``.
    cfg = dataclasses.replace(SMALL_CFG, frame_taper=4)
    (got,) = _correlate(pairs, cfg, None, (False,))
    corr = KernelCorrelator(cfg, dtype=torch.float64)
    x = corr.channels(pairs.frame) * frame_taper(60, 80, 4, torch.float64)
    want = corr(x, corr.fit(corr.channels(pairs.keyframe)), pairs.resolution)
    torch.testing.assert_close(got.t_xy, want.t_xy, rtol=0, atol=1e-7)  # metres; r_k is millimetres
    (plain,) = _correlate(pairs, SMALL_CFG, None, (False,))
    assert float((plain.t_xy - got.t_xy).abs().max()) > 1e-5  # the taper moves the matches
