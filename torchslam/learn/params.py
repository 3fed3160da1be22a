"""Learnable config values and parameter checkpoints.

``learnable(cfg, ["kcc.sigma", "kcc.lam"])`` turns named float fields of a (nested, frozen)
config dataclass into ``nn.Parameter``s held by a :class:`LearnableParams` module. Positive
values are held as their logarithm, so gradient steps can never make σ or λ negative; other
floats are held as they are. ``LearnableParams.apply(cfg)`` writes the current values back into a
config (as plain floats) for ordinary, non-differentiable runs.

A checkpoint is a ``torch.save`` of plain data only (tensors, dicts, strings, numbers), read back
with ``weights_only=True``, so loading one never runs code::

    {"format": "torchslam-params", "version": 1, "kind": "config" | "module",
     "config_type": "NISlamConfig" | None, "values": {"kcc.sigma": 0.23, ...},
     "state_dict": {...}, "extra": {...}}

``kind == "config"`` checkpoints (from :class:`LearnableParams`) carry ``values`` that
``torchslam run --params`` applies; ``kind == "module"`` ones hold another module's weights
(e.g. :class:`~torchslam.learn.PairWeightNet`) and have no config values.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, load_checkpoint
from ..errors import ConfigError
from ..optim import positive_parameter, positive_value

__all__ = [
    "CHECKPOINT_FORMAT",
    "LearnableParams",
    "checkpoint_overrides",
    "checkpoint_values",
    "learnable",
    "load_checkpoint",
    "save_checkpoint",
]



def _field_type(cls: type, name: str) -> Any:
    return typing.get_type_hints(cls)[name]


def _resolve_key(cfg: Any, key: str) -> float:
    """The current float value of dotted ``key`` in ``cfg``; ConfigError naming the key otherwise."""
    if not isinstance(key, str) or not key:
        raise ConfigError(f"names: expected dotted config keys such as 'kcc.sigma', got {key!r}")
    node = cfg
    parts = key.split(".")
    for depth, part in enumerate(parts):
        if not dataclasses.is_dataclass(node):
            raise ConfigError(f"{key}: {'.'.join(parts[:depth])} is not a config section")
        fields = {f.name for f in dataclasses.fields(node)}
        if part not in fields:
            raise ConfigError(f"{key}: unknown key for {type(node).__name__}; valid keys: {', '.join(sorted(fields))}")
        if depth == len(parts) - 1:
            tp = _field_type(type(node), part)
            value = getattr(node, part)
            if tp is not float or isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{key}: only float values can be learned, {type(node).__name__}.{part} is {tp!r}")
            return float(value)
        node = getattr(node, part)
    raise ConfigError(f"{key}: empty key")  # unreachable: split gives at least one part


def _replace(cfg: Any, parts: list[str], value: float) -> Any:
    if len(parts) == 1:
        return dataclasses.replace(cfg, **{parts[0]: value})
    return dataclasses.replace(cfg, **{parts[0]: _replace(getattr(cfg, parts[0]), parts[1:], value)})


def _slot(key: str) -> str:
    # nn.Module attribute names cannot contain dots.
    return key.replace(".", "__")


class LearnableParams(nn.Module):
    """Named config values held as ``nn.Parameter``s (float64, 0-d).

    Build it with :func:`learnable`. A positive initial value is held as ``log(value)`` (the
    value is then ``exp`` of the parameter and stays positive); any other float is held as is.

    Attributes:
        names: the dotted keys, in the order given.
        config_type: name of the config dataclass the keys belong to (e.g. ``"NISlamConfig"``).
        log_space: for each key, whether it is held in log space.
    """

    def __init__(self, names: Sequence[str], initial: Sequence[float], config_type: str, log_space: Sequence[bool]):
        super().__init__()
        if not (len(names) == len(initial) == len(log_space)):
            raise ConfigError(f"names: expected as many initial values as names, got {len(names)} and {len(initial)}")
        self.names = tuple(names)
        self.config_type = config_type
        self.log_space = tuple(bool(b) for b in log_space)
        self.raw = nn.ParameterDict()
        for key, v, log in zip(self.names, initial, self.log_space):
            self.raw[_slot(key)] = positive_parameter(v, key) if log else nn.Parameter(torch.tensor(float(v), dtype=torch.float64))

    def value(self, key: str) -> Tensor:
        """Return the differentiable 0-d float64 value of ``key``."""
        if key not in self.names:
            raise ConfigError(f"{key}: not learnable here; learnable keys: {', '.join(self.names)}")
        p = self.raw[_slot(key)]
        return positive_value(p) if self.log_space[self.names.index(key)] else p

    def resolve(self, cfg: Any, key: str) -> Tensor | float:
        """``key``'s learned value as a tensor if it is learnable here, else its float in ``cfg``."""
        return self.value(key) if key in self.names else _resolve_key(cfg, key)

    def forward(self) -> dict[str, Tensor]:
        """Return every learned value, ``{key: 0-d tensor}``, differentiable."""
        return {k: self.value(k) for k in self.names}

    def floats(self) -> dict[str, float]:
        """Return the current values as plain (detached) floats."""
        return {k: float(self.value(k).detach()) for k in self.names}

    def apply(self, cfg: Any) -> Any:
        """Return ``cfg`` with the learned keys set to their current values (plain floats).

        Raises:
            ConfigError: when ``cfg`` is not a ``config_type`` or lacks a key.
        """
        if type(cfg).__name__ != self.config_type:
            raise ConfigError(f"cfg: these parameters belong to {self.config_type}, got {type(cfg).__name__}")
        for key, v in self.floats().items():
            _resolve_key(cfg, key)
            cfg = _replace(cfg, key.split("."), v)
        return cfg


def learnable(cfg: Any, names: Sequence[str]) -> LearnableParams:
    """Make named float values of a config dataclass learnable.

    Args:
        cfg: a config dataclass instance (e.g. ``NISlamConfig()``); its values are the initial ones.
        names: dotted keys of float fields, e.g. ``["kcc.sigma", "kcc.lam", "kcc.temperature"]``.

    Returns:
        LearnableParams holding one parameter per key.

    Raises:
        ConfigError: for an unknown key, a key that is not a float field, a repeated key, or no keys.
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise ConfigError(f"cfg: expected a config dataclass instance, got {type(cfg).__name__}")
    if isinstance(names, str):
        raise ConfigError(f"names: expected a sequence of dotted keys, got the string {names!r}")
    names = list(names)
    if not names:
        raise ConfigError("names: expected at least one config key to learn, got none")
    seen = set()
    for key in names:
        if key in seen:
            raise ConfigError(f"{key}: named twice in names")
        seen.add(key)
    values = [_resolve_key(cfg, key) for key in names]
    return LearnableParams(names, values, type(cfg).__name__, [v > 0 for v in values])


# ----------------------------------------------------------------------------------------------
# checkpoints


def _plain(obj: Any, where: str) -> Any:
    """Check that ``obj`` is plain data ``weights_only`` loading accepts; tensors are detached to CPU."""
    if isinstance(obj, Tensor):
        return obj.detach().cpu().clone()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise ConfigError(f"{where}: keys must be strings, got {k!r}")
            out[k] = _plain(v, f"{where}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise ConfigError(f"{where}: a checkpoint holds only tensors, numbers, strings, lists and dicts, got {type(obj).__name__}")


def save_checkpoint(path: str | os.PathLike, params: nn.Module, extra: Mapping[str, Any] | None = None) -> Path:
    """Save learned parameters as plain data (see the module docstring for the layout).

    Args:
        path: file to write (its folder is created).
        params: a :class:`LearnableParams` (a ``"config"`` checkpoint with its values) or any other
            module (a ``"module"`` checkpoint of its ``state_dict``).
        extra: plain data stored beside them (training settings, metrics, architecture).

    Returns:
        The path written.
    """
    if not isinstance(params, nn.Module):
        raise ConfigError(f"params: expected an nn.Module, got {type(params).__name__}")
    is_config = isinstance(params, LearnableParams)
    doc = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "kind": "config" if is_config else "module",
        "module": type(params).__name__,
        "config_type": params.config_type if is_config else None,
        "values": params.floats() if is_config else {},
        "log_space": list(params.log_space) if is_config else [],
        "state_dict": _plain(dict(params.state_dict()), "state_dict"),
        "extra": _plain(dict(extra or {}), "extra"),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(doc, path)
    return path


def checkpoint_values(path: str | os.PathLike, config_cls: type, system: str | None = None) -> dict[str, float]:
    """Read a ``"config"`` checkpoint's values for a config class, checked against it.

    Args:
        path: the checkpoint file.
        config_cls: the config dataclass the values are to override (e.g. ``NISlamConfig``).
        system: the system's name, for messages.

    Returns:
        ``{dotted key: float}``.

    Raises:
        DataFormatError: for an unreadable file.
        ConfigError: naming the file when the checkpoint holds a module rather than config values,
            belongs to another config class (another system), or names an unknown or non-float key.
    """
    return _config_values(load_checkpoint(path), path, config_cls, system)


def _config_values(doc: dict[str, Any], path, config_cls: type, system: str | None) -> dict[str, float]:
    what = f"system {system!r} ({config_cls.__name__})" if system else config_cls.__name__
    if doc["kind"] != "config":
        raise ConfigError(
            f"{path}: this checkpoint holds the weights of a {doc.get('module')} module, not config values; "
            f"it cannot override the config of {what}"
        )
    if doc.get("config_type") != config_cls.__name__:
        raise ConfigError(f"{path}: checkpoint values belong to {doc.get('config_type')}, not to {what}")
    base = config_cls()
    for key in doc["values"]:
        try:
            _resolve_key(base, key)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from exc
    return {k: float(v) for k, v in doc["values"].items()}


# Module checkpoints that a run can apply, and the config values that select them: the module's
# name -> the dotted key of the weights' path, and the keys set beside it.
RUN_MODULES: dict[str, tuple[str, dict[str, str]]] = {
    "KCCFeatureNet": ("kcc.features_weights", {"kcc.features": "learned"}),
}


def checkpoint_overrides(path: str | os.PathLike, config_cls: type, system: str | None = None) -> dict[str, Any]:
    """The config overrides ``torchslam run --params CKPT`` applies for a checkpoint.

    A ``"config"`` checkpoint gives its values (``checkpoint_values``). A ``"module"`` checkpoint
    of a network a run can use (``RUN_MODULES``: the learned KCC channels) selects it: e.g.
    ``{"kcc.features": "learned", "kcc.features_weights": "/abs/path/params.pt"}``.

    Raises:
        DataFormatError: for an unreadable file.
        ConfigError: naming the file when the checkpoint fits neither, or not this system's config.
    """
    doc = load_checkpoint(path)
    if doc["kind"] == "module" and doc.get("module") in RUN_MODULES:
        key, beside = RUN_MODULES[doc["module"]]
        base = config_cls()
        node = base
        for part in key.split(".")[:-1]:
            node = getattr(node, part, None)
        if node is None or not hasattr(node, key.split(".")[-1]):
            what = f"system {system!r} ({config_cls.__name__})" if system else config_cls.__name__
            raise ConfigError(f"{path}: this checkpoint holds {doc['module']} weights, which {what} does not use")
        return {**beside, key: str(Path(path).expanduser().resolve())}
    return _config_values(doc, path, config_cls, system)

