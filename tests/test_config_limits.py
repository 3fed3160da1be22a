"""Every numeric field of every config class has a declared limit, NaN is refused everywhere, and
the command line takes every float spelling."""

import dataclasses
import importlib
import math
import pkgutil
import warnings

import pytest

import torchslam
from torchslam.cli import main
from torchslam.config import config_from_dict, load_config, load_yaml, parse_overrides
from torchslam.errors import ConfigError, Limit, check_limits, numeric_fields
from torchslam.systems.nislam import NISlamConfig
from torchslam.app.run import resolve_config


def _config_classes() -> list[type]:
    """Every dataclass in torchslam named ``*Config`` and every dataclass nested in one, plus ImuNoise."""
    found: dict[str, type] = {}
    with warnings.catch_warnings():  # walk_packages imports the old torchslam.slam package too
        warnings.simplefilter("ignore", FutureWarning)
        modules = list(pkgutil.walk_packages(torchslam.__path__, "torchslam."))
    for mod in modules:
        if mod.name == "torchslam.__main__" or mod.name.startswith("torchslam.slam"):
            continue  # the entry point, and the old paths that only alias new ones
        module = importlib.import_module(mod.name)
        for obj in vars(module).values():
            if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__:
                if obj.__name__.endswith("Config") or obj.__name__ == "ImuNoise":
                    found[f"{obj.__module__}.{obj.__qualname__}"] = obj
    todo = list(found.values())
    while todo:
        cls = todo.pop()
        for f in dataclasses.fields(cls):
            default = getattr(cls(), f.name)
            if dataclasses.is_dataclass(default) and f"{type(default).__module__}.{type(default).__qualname__}" not in found:
                found[f"{type(default).__module__}.{type(default).__qualname__}"] = type(default)
                todo.append(type(default))
    return sorted(found.values(), key=lambda c: c.__name__)


CONFIGS = _config_classes()


def test_the_walk_finds_the_configs():
    names = {c.__name__ for c in CONFIGS}
    expected = {
        "NISlamConfig", "LoopConfig", "KCCConfig", "GCSlamConfig", "SparseConfig", "DenseConfig", "MILDConfig",
        "DataConfig", "SyntheticConfig", "ImuNoise", "LMConfig", "FastGOConfig", "KCCTrainConfig", "PairNetTrainConfig",
    }
    assert expected <= names


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_every_numeric_field_has_a_declared_limit_that_is_checked(cls):
    assert isinstance(cls.__dict__.get("LIMITS"), dict), f"{cls.__name__} declares no LIMITS"
    assert set(cls.LIMITS) == set(numeric_fields(cls))
    assert all(isinstance(v, Limit) for v in cls.LIMITS.values())
    check_limits(cls())  # the defaults are within their own limits


def _float_fields(cls):
    return [(n, shape) for n, (shape, integer) in numeric_fields(cls).items() if not integer]


FLOAT_FIELDS = [(cls, name, shape) for cls in CONFIGS for name, shape in _float_fields(cls)]
INT_FIELDS = [(cls, n, shape) for cls in CONFIGS for n, (shape, integer) in numeric_fields(cls).items() if integer]


def _with(cls, name, shape, value):
    return {name: (value,) if shape == "tuple" else value}


@pytest.mark.parametrize("cls,name,shape", FLOAT_FIELDS, ids=lambda x: getattr(x, "__name__", x))
def test_nan_is_refused_in_every_float_field(cls, name, shape):
    with pytest.raises(ConfigError, match=rf"{cls.__name__}\.{name}: expected"):
        dataclasses.replace(cls(), **_with(cls, name, shape, math.nan))
    # The same through config loading, which names the key.
    with pytest.raises(ConfigError, match=rf"^test: {name}: expected .*got nan"):
        config_from_dict(cls, _with(cls, name, shape, math.nan), source="test")


@pytest.mark.parametrize("cls,name,shape", FLOAT_FIELDS, ids=lambda x: getattr(x, "__name__", x))
def test_inf_only_where_the_field_allows_it(cls, name, shape):
    limit = cls.LIMITS[name]
    for value in (math.inf, -math.inf):
        inside = limit.allow_inf and limit.check(value, False) is None
        if inside:
            assert getattr(dataclasses.replace(cls(), **_with(cls, name, shape, value)), name) in (value, (value,))
        else:
            with pytest.raises(ConfigError, match=name):
                dataclasses.replace(cls(), **_with(cls, name, shape, value))


@pytest.mark.parametrize("cls,name,shape", INT_FIELDS, ids=lambda x: getattr(x, "__name__", x))
def test_int_fields_refuse_fractions(cls, name, shape):
    with pytest.raises(ConfigError, match=name):
        dataclasses.replace(cls(), **_with(cls, name, shape, 2.5))
    with pytest.raises(ConfigError, match=rf"{name}: expected an integer, got 2.5"):
        config_from_dict(cls, _with(cls, name, shape, 2.5))


def test_limit_describes_and_checks():
    assert Limit(gt=0).describe(False) == "a finite number > 0"
    assert Limit(ge=1, odd=True).describe(True) == "an odd integer >= 1"
    assert Limit(gt=0, allow_inf=True).describe(False) == "a number > 0 (inf allowed)"
    assert Limit(gt=0).check(1e-300, False) is None and Limit(gt=0).check(0.0, False) == "out of range"
    assert Limit().check(True, True) == "not a number" and Limit().check(2.0, True) == "not an integer"
    assert Limit(ge=1, odd=True).check(4, True) == "out of range"


@pytest.mark.parametrize(
    "setting,key",
    [
        ("max_jump_m=-1", "max_jump_m"),
        ("attitude_max_gap=.nan", "attitude_max_gap"),
        ("attitude_time_offset=.inf", "attitude_time_offset"),
        ("map_voxel=.nan", "map_voxel"),
        ("loop.min_score=.nan", r"loop\.min_score"),
        ("min_valid_points=-5", "min_valid_points"),
        ("kcc.sigma=nan", r"kcc\.sigma"),
        ("data.max_gap=-0.1", r"max_gap"),
    ],
)
def test_run_refuses_meaningless_values(setting, key, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--system", "nislam", "--data", "synthetic", "--out", str(out), "--set", setting]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and pytest.importorskip("re").search(rf"{key}: expected", err), err
    assert not out.exists()


def test_gcslam_settings_are_checked_too(tmp_path, capsys):
    for setting in ("map_voxel=.nan", "dense.tol=-1", "sparse.huber_delta=.inf", "mild.min_score=.nan"):
        assert main(["run", "--system", "gcslam", "--data", "synthetic", "--out", str(tmp_path / "r"), "--set", setting]) == 2
        assert setting.split("=")[0] + ": expected" in capsys.readouterr().err


@pytest.mark.parametrize(
    "raw,value",
    [("2e-1", 0.2), ("1E3", 1000.0), (".5", 0.5), ("5.", 5.0), ("-0.0", -0.0), ("1_000.5", 1000.5), (" 3 ", 3.0)],
)
def test_every_float_spelling_is_a_number(raw, value):
    cfg, _, _ = resolve_config("nislam", None, [f"attitude_time_offset={raw}"])
    assert cfg.attitude_time_offset == value and isinstance(cfg.attitude_time_offset, float)
    assert math.copysign(1, cfg.attitude_time_offset) == math.copysign(1, value)


def test_float_spellings_in_files_and_sections(tmp_path):
    cfg, _, _ = resolve_config("nislam", None, ["kcc.sigma=2e-1", "kcc.T_M=1E3", "max_jump_m=inf"])
    assert (cfg.kcc.sigma, cfg.kcc.T_M, cfg.max_jump_m) == (0.2, 1000.0, math.inf)
    path = tmp_path / "c.yaml"
    path.write_text("kcc:\n  sigma: 2e-1\n  lam: 1E-2\n")
    cfg = load_config(NISlamConfig, path)
    assert (cfg.kcc.sigma, cfg.kcc.lam) == (0.2, 0.01)
    with pytest.raises(ConfigError, match=r"kcc\.sigma: expected a finite number > 0, got inf"):
        resolve_config("nislam", None, ["kcc.sigma=inf"])
    with pytest.raises(ConfigError, match=r"kcc\.sigma: expected a number, got 'abc'"):
        resolve_config("nislam", None, ["kcc.sigma=abc"])


def test_integers_where_ints_are_expected():
    cfg, _, _ = resolve_config("nislam", None, ["min_valid_points=1_000", "pixel_stride=+2", "kcc.ortho_width='480'"])
    assert (cfg.min_valid_points, cfg.pixel_stride, cfg.kcc.ortho_width) == (1000, 2, 480)
    for bad in ("2.5", "2e3", "1.0"):
        with pytest.raises(ConfigError, match=r"min_valid_points: expected an integer"):
            resolve_config("nislam", None, [f"min_valid_points={bad}"])


def test_duplicate_yaml_key_names_both_lines(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text("max_jump_m: 0.2\nkcc:\n  sigma: 0.3\n  lam: 0.1\n  sigma: 0.4\n")
    for load in (lambda: load_config(NISlamConfig, path), lambda: resolve_config("nislam", path, [])):
        with pytest.raises(ConfigError, match=rf"^{path}:5: duplicate key 'sigma' \(first given at {path}:3\)$"):
            load()
    path.write_text("max_jump_m: 0.2\n\nmax_jump_m: 0.3\n")
    with pytest.raises(ConfigError, match=r"dup.yaml:3: duplicate key 'max_jump_m' \(first given at .*dup.yaml:1\)"):
        resolve_config("nislam", path, [])
    # Merge keys are not duplicates; an explicit key after a merge overrides it.
    assert load_yaml("a: &x {s: 1, t: 2}\nb:\n  <<: *x\n  s: 3\n")["b"] == {"s": 3, "t": 2}
    with pytest.raises(ConfigError, match=r"--set k:1: duplicate key 'a'"):
        load_yaml("{a: 1, a: 2}", "--set k")
    assert parse_overrides(["a.b={x: 1}"]) == {"a": {"b": {"x": 1}}}
