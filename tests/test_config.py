import enum
from dataclasses import dataclass, field

import pytest
import yaml

from torchslam.config import config_from_dict, config_to_dict, load_config, parse_overrides, save_config
from torchslam.errors import ConfigError

from tests._helpers import REPO_ROOT


class Mode(enum.Enum):
    FAST = "fast"
    EXACT = "exact"


@dataclass(frozen=True)
class Inner:
    sigma: float = 0.2
    steps: int = 3


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    mode: Mode = Mode.FAST
    end: int | None = None
    flag: bool = False
    inner: Inner = field(default_factory=Inner)


def test_defaults_file_and_overrides_layer(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: y\ninner:\n  sigma: 0.5\n")
    cfg = load_config(Outer, path, ["inner.steps=7", "mode=exact", "end=12", "flag=true"])
    assert cfg == Outer(name="y", mode=Mode.EXACT, end=12, flag=True, inner=Inner(sigma=0.5, steps=7))
    # int accepted for a float field, None for an optional one
    assert load_config(Outer, None, ["inner.sigma=1", "end=null"]).inner.sigma == 1.0


def test_roundtrip_through_saved_yaml(tmp_path):
    cfg = Outer(name="z", mode=Mode.EXACT, inner=Inner(0.3, 4))
    save_config(cfg, tmp_path / "s.yaml")
    assert yaml.safe_load((tmp_path / "s.yaml").read_text())["mode"] == "exact"
    assert load_config(Outer, tmp_path / "s.yaml") == cfg
    assert config_from_dict(Outer, config_to_dict(cfg)) == cfg


def test_unknown_keys_and_bad_values_name_the_key_and_source(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("inner:\n  sigmaa: 0.5\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: inner.sigmaa: unknown key for Inner; valid keys: sigma, steps"):
        load_config(Outer, path)
    with pytest.raises(ConfigError, match=r"--set: mode: 'slow' is not one of \['fast', 'exact'\]"):
        load_config(Outer, None, ["mode=slow"])
    with pytest.raises(ConfigError, match=r"inner.steps: expected an integer, got 'many'"):
        load_config(Outer, None, ["inner.steps=many"])
    with pytest.raises(ConfigError, match=r"flag: expected true or false"):
        load_config(Outer, None, ["flag=3"])
    with pytest.raises(ConfigError, match=r"expected key=value"):
        parse_overrides(["novalue"])


def test_malformed_yaml_reports_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("name: a\ninner: [1, 2\nflag: true\n")
    with pytest.raises(ConfigError, match=r"broken.yaml:\d+:\d+: malformed YAML"):
        load_config(Outer, path)
    path.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping at the top level"):
        load_config(Outer, path)
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(Outer, tmp_path / "missing.yaml")


def _missing_keys(defaults: dict, stated: dict, prefix: str = "") -> list[str]:
    out = []
    for key, value in defaults.items():
        if key not in stated:
            out.append(prefix + key)
        elif isinstance(value, dict) and isinstance(stated[key], dict):
            out += _missing_keys(value, stated[key], f"{prefix}{key}.")
    return out


@pytest.mark.parametrize("system", ["nislam", "gcslam"])
def test_each_system_yaml_states_every_default(system):
    """configs/<system>.yaml is the documentation of the defaults: complete and equal to the code."""
    from torchslam.systems.registry import get_system

    cls = get_system(system).config_cls
    path = REPO_ROOT / "configs" / f"{system}.yaml"
    assert load_config(cls, path) == cls()
    assert _missing_keys(config_to_dict(cls()), yaml.safe_load(path.read_text())) == []


def test_nislam_fast_preset_changes_only_the_pixel_stride():
    from torchslam.config import config_to_dict
    from torchslam.systems.nislam import NISlamConfig

    fast = load_config(NISlamConfig, REPO_ROOT / "configs" / "nislam_fast.yaml")
    assert fast.pixel_stride == 2
    a, b = config_to_dict(fast), config_to_dict(NISlamConfig())
    assert {k for k in a if a[k] != b[k]} == {"pixel_stride"}


def test_nislam_faster_preset_changes_only_stride_orthographic_size_and_where_frames_are_prepared():
    from torchslam.config import config_to_dict
    from torchslam.systems.nislam import NISlamConfig

    fast = load_config(NISlamConfig, REPO_ROOT / "configs" / "nislam_faster.yaml")
    assert (fast.pixel_stride, fast.kcc.ortho_height, fast.kcc.ortho_width) == (2, 240, 320)
    assert fast.prepare_ahead_in == "process"  # the same trajectory as on a thread (tests/systems/test_ahead_process.py)
    a, b = config_to_dict(fast), config_to_dict(NISlamConfig())
    assert {k for k in a if a[k] != b[k]} == {"pixel_stride", "prepare_ahead_in", "kcc"}
    assert {k for k in a["kcc"] if a["kcc"][k] != b["kcc"][k]} == {"ortho_height", "ortho_width"}


def test_nislam_accurate_preset_changes_only_the_orthographic_size():
    from torchslam.config import config_to_dict
    from torchslam.systems.nislam import NISlamConfig

    acc = load_config(NISlamConfig, REPO_ROOT / "configs" / "nislam_accurate.yaml")
    assert (acc.kcc.ortho_height, acc.kcc.ortho_width) == (480, 640)
    a, b = config_to_dict(acc), config_to_dict(NISlamConfig())
    assert {k for k in a if a[k] != b[k]} == {"kcc"}
    assert {k for k in a["kcc"] if a["kcc"][k] != b["kcc"][k]} == {"ortho_height", "ortho_width"}
