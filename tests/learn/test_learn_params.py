"""The learnable-config hook and parameter checkpoints."""

from __future__ import annotations

import dataclasses
import math
import argparse
import pickle

import pytest
import torch

from torchslam.errors import ConfigError, DataFormatError
from torchslam.learn import PairWeightNet, checkpoint_values, learnable, load_checkpoint, save_checkpoint
from torchslam.systems.gcslam import GCSlamConfig
from torchslam.systems.nislam import NISlamConfig

KEYS = ["kcc.sigma", "kcc.lam", "kcc.temperature"]


@dataclasses.dataclass(frozen=True)
class _Inner:
    offset: float = -0.5
    scale: float = 2.0


@dataclasses.dataclass(frozen=True)
class _Outer:
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    count: int = 3


def test_learnable_holds_config_values_and_applies_them_back():
    cfg = NISlamConfig()
    p = learnable(cfg, KEYS)
    assert p.names == tuple(KEYS) and p.config_type == "NISlamConfig"
    assert len(list(p.parameters())) == 3
    for key, expected in zip(KEYS, (cfg.kcc.sigma, cfg.kcc.lam, cfg.kcc.temperature)):
        assert p.value(key).dtype == torch.float64
        assert float(p.value(key).detach()) == pytest.approx(expected, rel=1e-12)
    # positive values live in log space: the raw parameter is log(value)
    assert float(p.raw["kcc__sigma"].detach()) == pytest.approx(math.log(0.2), rel=1e-12)
    with torch.no_grad():
        p.raw["kcc__sigma"].fill_(math.log(0.35))
        p.raw["kcc__lam"].fill_(math.log(0.02))
    out = p.apply(cfg)
    assert out.kcc.sigma == pytest.approx(0.35) and out.kcc.lam == pytest.approx(0.02)
    assert isinstance(out.kcc.sigma, float)
    # everything else is unchanged, and the input config is not mutated
    assert dataclasses.replace(out.kcc, sigma=cfg.kcc.sigma, lam=cfg.kcc.lam) == cfg.kcc
    assert out.loop == cfg.loop and cfg.kcc.sigma == 0.2
    # resolve: learned keys give tensors, the others the config's float
    assert isinstance(p.resolve(cfg, "kcc.sigma"), torch.Tensor)
    assert p.resolve(cfg, "kcc.T_c") == cfg.kcc.T_c


def test_gradients_reach_the_log_parameters():
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    v = p.value("kcc.sigma")
    (v * 3.0).backward()
    # d(3 exp(u))/du = 3 exp(u) = 3 sigma
    assert float(p.raw["kcc__sigma"].grad) == pytest.approx(3 * 0.2, rel=1e-12)


def test_non_positive_values_are_held_linearly():
    p = learnable(_Outer(), ["inner.offset", "inner.scale"])
    assert p.log_space == (False, True)
    assert float(p.raw["inner__offset"].detach()) == -0.5
    assert float(p.value("inner.scale").detach()) == pytest.approx(2.0)
    with torch.no_grad():
        p.raw["inner__offset"].fill_(-2.0)
    assert p.apply(_Outer()).inner.offset == -2.0


@pytest.mark.parametrize(
    "names, match",
    [
        (["kcc.sigmaa"], r"kcc\.sigmaa: unknown key for KCCConfig"),
        (["nope"], r"nope: unknown key for NISlamConfig"),
        (["kcc.ortho_height"], r"kcc\.ortho_height: only float values"),
        (["kcc.subpixel"], r"kcc\.subpixel: only float values"),
        (["attitude"], r"attitude: only float values"),
        (["kcc.soft_argmax"], r"kcc\.soft_argmax: only float values"),
        (["map_voxel.x"], r"map_voxel\.x: map_voxel is not a config section"),
        (["kcc.sigma", "kcc.sigma"], r"kcc\.sigma: named twice"),
        ([], r"at least one"),
        ("kcc.sigma", r"not the string|sequence"),
    ],
)
def test_bad_keys_raise_naming_the_key(names, match):
    with pytest.raises(ConfigError, match=match):
        learnable(NISlamConfig(), names)


def test_apply_to_another_config_type_raises():
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    with pytest.raises(ConfigError, match="belong to NISlamConfig"):
        p.apply(GCSlamConfig())
    with pytest.raises(ConfigError, match="cfg: expected a config dataclass"):
        learnable(NISlamConfig, ["kcc.sigma"])


def test_checkpoint_round_trip(tmp_path):
    cfg = NISlamConfig()
    p = learnable(cfg, KEYS)
    with torch.no_grad():
        p.raw["kcc__sigma"].add_(0.7)
        p.raw["kcc__temperature"].sub_(0.4)
    path = save_checkpoint(tmp_path / "sub" / "params.pt", p, {"metrics": {"rms_px": 0.1}, "seeds": [1, 2], "t": torch.ones(2)})
    doc = load_checkpoint(path)
    assert doc["kind"] == "config" and doc["config_type"] == "NISlamConfig"
    assert doc["values"] == pytest.approx(p.floats())
    assert doc["extra"]["metrics"] == {"rms_px": 0.1} and doc["extra"]["seeds"] == [1, 2]
    assert torch.equal(doc["extra"]["t"], torch.ones(2))
    # the state dict restores a fresh module exactly
    q = learnable(cfg, KEYS)
    q.load_state_dict(doc["state_dict"])
    for key in KEYS:
        assert torch.equal(q.value(key), p.value(key))
    assert q.apply(cfg) == p.apply(cfg)
    assert checkpoint_values(path, NISlamConfig, "nislam") == pytest.approx(p.floats())


def test_module_checkpoint_round_trip(tmp_path):
    torch.manual_seed(3)
    net = PairWeightNet(hidden=5)
    with torch.no_grad():
        for prm in net.parameters():
            prm.add_(0.1 * torch.randn_like(prm))
    path = save_checkpoint(tmp_path / "net.pt", net, {"architecture": net.architecture()})
    doc = load_checkpoint(path)
    assert doc["kind"] == "module" and doc["module"] == "PairWeightNet" and doc["values"] == {}
    net2 = PairWeightNet(**doc["extra"]["architecture"])
    net2.load_state_dict(doc["state_dict"])
    x = torch.randn(7, 4, dtype=torch.float64)
    assert torch.equal(net(x), net2(x))


class _Evil:
    def __reduce__(self):
        return (print, ("loaded code ran",))


def test_load_rejects_bad_files_naming_them(tmp_path):
    with pytest.raises(DataFormatError, match=r"missing\.pt: no such checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(DataFormatError, match=r"junk\.pt: not a readable"):
        load_checkpoint(junk)
    evil = tmp_path / "evil.pt"
    with evil.open("wb") as fh:
        pickle.dump({"format": "torchslam-params", "x": _Evil()}, fh, protocol=2)
    with pytest.raises(DataFormatError, match=r"evil\.pt: not a readable"):  # weights_only refuses it
        load_checkpoint(evil)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.ones(3)}, other)
    with pytest.raises(DataFormatError, match=r"other\.pt: not a torchslam parameter checkpoint"):
        load_checkpoint(other)
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    bad_value = tmp_path / "nan.pt"
    save_checkpoint(bad_value, p)
    doc = torch.load(bad_value, weights_only=True)
    doc["values"]["kcc.sigma"] = float("nan")
    torch.save(doc, bad_value)
    with pytest.raises(DataFormatError, match=r"nan\.pt: value 'kcc.sigma'"):
        load_checkpoint(bad_value)


def test_unsafe_pickle_checkpoint_is_refused_in_one_line_naming_file_and_object(tmp_path, capsys):
    # torch.save of an arbitrary object (and a hand-written pickle that would call print) beside
    # valid checkpoint fields: weights_only refuses both; the message is one complete line.
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    save_checkpoint(tmp_path / "good.pt", p)
    doc = torch.load(tmp_path / "good.pt", weights_only=True)
    doc["extra"]["args"] = argparse.Namespace(lr=0.01)
    unsafe = tmp_path / "unsafe.pt"
    torch.save(doc, unsafe)
    evil = tmp_path / "evil.pt"
    with evil.open("wb") as fh:
        pickle.dump({"format": "torchslam-params", "x": _Evil()}, fh, protocol=2)
    for path, name in ((unsafe, "argparse.Namespace"), (evil, "print")):
        with pytest.raises(DataFormatError) as info:
            load_checkpoint(path)
        msg = str(info.value)
        assert msg.startswith(f"{path}: not a readable torchslam checkpoint (refused as an unsafe pickle")
        assert f"would import {name};" in msg and msg.endswith("never runs code)")
        assert "\n" not in msg and "\x1b" not in msg and "weights_only" not in msg and "Re-running" not in msg
    assert "loaded code ran" not in capsys.readouterr().out
    # other unreadable files keep a one-line reason too
    for data, reason in ((b"", "the file ends early"), (b"PK\x03\x04junk", "not a ZIP archive)"), (b"not a checkpoint", "not plain pickled data")):
        (tmp_path / "bad.pt").write_bytes(data)
        with pytest.raises(DataFormatError, match=r"bad\.pt: not a readable torchslam checkpoint \(") as info:
            load_checkpoint(tmp_path / "bad.pt")
        assert reason in str(info.value) and "\n" not in str(info.value)


def test_checkpoint_values_reject_other_systems_modules_and_unknown_keys(tmp_path):
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    good = save_checkpoint(tmp_path / "good.pt", p)
    with pytest.raises(ConfigError, match=r"good\.pt: checkpoint values belong to NISlamConfig, not to system 'gcslam'"):
        checkpoint_values(good, GCSlamConfig, "gcslam")
    net = save_checkpoint(tmp_path / "net.pt", PairWeightNet())
    with pytest.raises(ConfigError, match=r"net\.pt: this checkpoint holds the weights of a PairWeightNet"):
        checkpoint_values(net, NISlamConfig, "nislam")
    doc = torch.load(good, weights_only=True)
    doc["values"] = {"kcc.sigmax": 0.3}
    unknown = tmp_path / "unknown.pt"
    torch.save(doc, unknown)
    with pytest.raises(ConfigError, match=r"unknown\.pt: kcc\.sigmax: unknown key"):
        checkpoint_values(unknown, NISlamConfig, "nislam")
    doc["values"] = {"kcc.ortho_width": 100.0}
    torch.save(doc, unknown)
    with pytest.raises(ConfigError, match=r"unknown\.pt: kcc\.ortho_width: only float values"):
        checkpoint_values(unknown, NISlamConfig, "nislam")


def test_save_rejects_non_plain_extra(tmp_path):
    p = learnable(NISlamConfig(), ["kcc.sigma"])
    with pytest.raises(ConfigError, match=r"extra\.cfg: a checkpoint holds only"):
        save_checkpoint(tmp_path / "x.pt", p, {"cfg": NISlamConfig()})
    with pytest.raises(ConfigError, match="params: expected an nn.Module"):
        save_checkpoint(tmp_path / "x.pt", {"a": 1})
