"""Configuration: frozen dataclass defaults in code, YAML files and ``key=value`` overrides on top.

A config is a (possibly nested) frozen dataclass. YAML files (the presets shipped in
``torchslam/presets/``, or any file) and command-line
``--set key=value`` pairs only override fields that exist; an unknown key is an error that names
the key (and the file). The resolved config is saved with every run.
"""

from __future__ import annotations

import dataclasses
import enum
import os
import types
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

import yaml

from .errors import ConfigError, FieldError, parse_choice

__all__ = [
    "config_file",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "load_yaml",
    "parse_overrides",
    "preset_names",
    "read_yaml_mapping",
    "save_config",
]

C = TypeVar("C")


def _field_types(cls) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _coerce(value: Any, tp: Any, key: str, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}{key}: invalid value {value!r}")
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}{key}: expected a mapping of {tp.__name__} fields, got {value!r}")
        return _build(tp, value, prefix=f"{key}.", where=where)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return parse_choice(tp, value, f"{where}{key}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}{key}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, str):
            # "+5", "1_000" and the like, whatever the YAML reader left as a string.
            try:
                return int(value.strip())
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):
            # YAML 1.1 reads "2e-1", "1E3" and "5e4" as strings (it wants "2.0e-1"): take every
            # spelling Python's float() takes; the field's limits then decide on inf and NaN.
            try:
                return float(value.strip())
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}{key}: expected a string, got {value!r}")
        return value
    if origin in (tuple, list):
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}{key}: expected a list, got {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], key, where) for v in value)
        if origin is tuple and args:
            if len(args) != len(value):
                raise ConfigError(f"{where}{key}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, key, where) for v, a in zip(value, args))
        return list(value) if origin is list else tuple(value)
    return value


def _resolve_aliases(cls, data: Mapping[str, Any], prefix: str, where: str) -> Mapping[str, Any]:
    """``data`` with the keys a config class renamed (``cls.ALIASES``: old key -> dotted new key) moved.

    A class that nests fields it once held flat (``SyntheticConfig.gyro_noise_density`` ->
    ``imu_noise.gyro_noise_density``) keeps reading the old keys. Giving a key both ways is an error.
    """
    aliases: Mapping[str, str] = getattr(cls, "ALIASES", {})
    if not any(k in aliases for k in data):
        return data
    out: dict[str, Any] = {k: v for k, v in data.items() if k not in aliases}
    for old, value in data.items():
        if old not in aliases:
            continue
        *sections, leaf = aliases[old].split(".")
        node = out
        for part in sections:
            child = node.get(part)
            child = dict(config_to_dict(child) if dataclasses.is_dataclass(child) else child or {})
            node[part] = child
            node = child
        if leaf in node:
            raise ConfigError(f"{where}{prefix}{old}: given twice, also as {prefix}{aliases[old]}")
        node[leaf] = value
    return out


def _build(cls, data: Mapping[str, Any], prefix: str = "", where: str = ""):
    types_ = _field_types(cls)
    data = _resolve_aliases(cls, data, prefix, where)
    unknown = sorted(set(data) - set(types_))
    if unknown:
        raise ConfigError(
            f"{where}{prefix}{unknown[0]}: unknown key for {cls.__name__}; valid keys: {', '.join(sorted(types_))}"
        )
    base = cls()
    kwargs = {}
    for name, value in data.items():
        tp = types_[name]
        current = getattr(base, name)
        if dataclasses.is_dataclass(tp) and isinstance(value, Mapping):
            # Renamed keys move before the defaults merge in, so they meet only what was given.
            value = _resolve_aliases(tp, value, f"{prefix}{name}.", where)
            merged = {**config_to_dict(current), **value} if current is not None else dict(value)
            kwargs[name] = _build(tp, merged, prefix=f"{prefix}{name}.", where=where)
        else:
            kwargs[name] = _coerce(value, tp, f"{prefix}{name}", where)
    try:
        return dataclasses.replace(base, **kwargs)
    except FieldError as exc:
        raise ConfigError(f"{where}{prefix}{exc.field}: {exc.reason}") from exc
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}{prefix.rstrip('.') or cls.__name__}: {exc}") from exc


def config_from_dict(cls: type[C], data: Mapping[str, Any] | None, source: str | None = None) -> C:
    """Build a config dataclass from a nested mapping; missing keys keep their defaults.

    Raises:
        ConfigError: for an unknown key or a value of the wrong type, naming the dotted key and
            ``source`` (a file name) when given.
    """
    where = f"{source}: " if source else ""
    if data is None:
        return cls()
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}expected a mapping at the top level, got {type(data).__name__}")
    return _build(cls, data, where=where)


def config_to_dict(cfg: Any) -> Any:
    """Turn a config dataclass into plain YAML/JSON-serialisable data."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, enum.Enum):
        return cfg.value
    if isinstance(cfg, (list, tuple)):
        return [config_to_dict(v) for v in cfg]
    return cfg


def parse_overrides(pairs: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """Turn ``["a.b=1", "c=foo"]`` into a nested mapping; values are parsed as YAML scalars."""
    out: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set {pair!r}: expected key=value")
        key, raw = pair.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"--set {pair!r}: empty key")
        try:
            value = load_yaml(raw, f"--set {key}") if raw.strip() else ""
        except ConfigError as exc:
            raise ConfigError(f"--set {key}: cannot parse value {raw!r} ({exc})") from exc
        _set_dotted(out, key, value, f"--set {key}")
    return out


def _set_dotted(out: dict[str, Any], key: str, value: Any, where: str) -> None:
    """Store ``value`` at the dotted ``key`` ("kcc.sigma") of the nested mapping ``out``."""
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"{where}: {part} is set to a value and used as a section")
    node[parts[-1]] = value


def nest_dotted(values: Mapping[str, Any], where: str = "") -> dict[str, Any]:
    """``{"kcc.sigma": 0.3}`` as ``{"kcc": {"sigma": 0.3}}``."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        _set_dotted(out, key, value, f"{where}{key}")
    return out


def deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` merged in, section by section (neither is modified)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(dict(out[k]), v)
        else:
            out[k] = v
    return out


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a mapping that repeats a key (PyYAML keeps the last silently)."""

    source = "<yaml>"

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node)
                line = key_node.start_mark.line + 1
                try:
                    first = seen.get(key)
                except TypeError:  # an unhashable key: PyYAML's own error follows
                    continue
                if first is not None:
                    raise ConfigError(f"{self.source}:{line}: duplicate key {key!r} (first given at {self.source}:{first})")
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str, source: str = "<yaml>") -> Any:
    """Parse YAML text with the safe loader, refusing duplicate keys: every YAML torchslam reads goes here.

    Args:
        text: the YAML document.
        source: what the text is (a file name, ``--set key``) for the messages.

    Raises:
        ConfigError: for malformed YAML (``source:line:column``), an unsafe tag, or a mapping
            with a duplicate key (naming both lines).
    """
    loader = _UniqueKeyLoader(text)
    loader.source = source
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        loc = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{source}{loc}: malformed YAML ({getattr(exc, 'problem', None) or exc})") from exc
    finally:
        loader.dispose()


def read_yaml_mapping(path: str | os.PathLike) -> dict[str, Any]:
    """Read a YAML file that holds a mapping (or nothing) through ``load_yaml``.

    Raises:
        ConfigError: naming the file for an unreadable file, malformed YAML, a duplicate key or
            a top level that is not a mapping.
    """
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config ({getattr(exc, 'strerror', None) or exc})") from exc
    loaded = load_yaml(text, str(path))
    if loaded is not None and not isinstance(loaded, Mapping):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(loaded).__name__}")
    return dict(loaded or {})


def load_config(cls: type[C], path: str | os.PathLike | None = None, overrides: list[str] | tuple[str, ...] = ()) -> C:
    """Load ``cls`` defaults, then a YAML file, then ``key=value`` overrides.

    Raises:
        ConfigError: for a missing or malformed file (with line and column), an unknown key, or a
            value of the wrong type.
    """
    data: dict[str, Any] = {}
    source = None
    if path is not None:
        source = str(path)
        data = read_yaml_mapping(path)
    over = parse_overrides(overrides)
    if over:
        # A bad key or value is reported against the layer it came from.
        config_from_dict(cls, data, source=source)
        source = "--set" if source is None else f"{source} + --set"
        data = deep_merge(data, over)
    return config_from_dict(cls, data, source=source)


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write the resolved config as YAML."""
    Path(path).write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


PRESET_SUFFIX = ".yaml"


def _presets_dir() -> Path:
    return Path(__file__).resolve().parent / "presets"


def preset_names() -> list[str]:
    """The config presets shipped inside the package (``torchslam/presets/*.yaml``), sorted."""
    return sorted(p.stem for p in _presets_dir().glob(f"*{PRESET_SUFFIX}"))


def config_file(name_or_path: str | os.PathLike) -> Path:
    """Resolve a ``--config`` argument: an existing file, else the name of a shipped preset.

    ``nislam_fast`` and ``nislam_fast.yaml`` both name the preset; a path that exists always wins
    over a preset of the same name.

    Raises:
        ConfigError: when the argument is neither an existing file nor a preset; the message lists
            the presets.
    """
    path = Path(name_or_path)
    if path.exists():
        return path
    text = str(name_or_path)
    stem = text[: -len(PRESET_SUFFIX)] if text.endswith(PRESET_SUFFIX) else text
    if stem in preset_names():
        return _presets_dir() / f"{stem}{PRESET_SUFFIX}"
    raise ConfigError(f"--config {text}: no such file, and not a preset (presets: {', '.join(preset_names())})")
