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
import math
import os
import pickle
import re
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..errors import ConfigError, DataFormatError
from ..optim import positive_parameter, positive_value

__all__ = [
    "CHECKPOINT_FORMAT",
    "LearnableParams",
    "checkpoint_values",
    "learnable",
    "load_checkpoint",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "torchslam-params"
CHECKPOINT_VERSION = 1


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


def _load_failure(exc: Exception) -> str:
    """One line saying why ``torch.load(weights_only=True)`` refused a file.

    PyTorch's own message for a refused pickle spans several lines of advice (ending in how to
    load the file with ``weights_only=False``, which would run its code); only the reason is kept.
    """
    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) and "Weights only load failed" in text:
        found = re.search(r"GLOBAL (\S+) was not an allowed global", text)
        if found:
            return (
                f"refused as an unsafe pickle that would import {found.group(1)}; torchslam reads "
                "checkpoints as plain data only, so that loading one never runs code"
            )
        reason = text.split("WeightsUnpickler error:", 1)[1] if "WeightsUnpickler error:" in text else ""
        reason = " ".join(reason.split("Check the documentation")[0].split())
        return f"not plain pickled data: {reason}" if reason else "not plain pickled data"
    if isinstance(exc, EOFError):
        return "the file ends early"
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    first = first.split(". ")[0][:200]
    return f"{exc.__class__.__name__}: {first}" if first else exc.__class__.__name__


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs).

    Returns:
        The stored dict (``format``, ``kind``, ``config_type``, ``values``, ``state_dict``, ``extra``...).

    Raises:
        DataFormatError: naming the file when it is missing, unreadable or not such a checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: no such checkpoint file")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle, zip and weights-only errors all mean "not a checkpoint"
        raise DataFormatError(f"{path}: not a readable torchslam checkpoint ({_load_failure(exc)})") from exc
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise DataFormatError(f"{path}: not a torchslam parameter checkpoint (no format: {CHECKPOINT_FORMAT!r})")
    if doc.get("version") != CHECKPOINT_VERSION:
        raise DataFormatError(f"{path}: checkpoint version {doc.get('version')!r}; this torchslam reads version {CHECKPOINT_VERSION}")
    for key, kind in (("values", dict), ("state_dict", dict), ("extra", dict), ("kind", str)):
        if not isinstance(doc.get(key), kind):
            raise DataFormatError(f"{path}: checkpoint field {key!r} is missing or not a {kind.__name__}")
    for key, v in doc["values"].items():
        if not isinstance(key, str) or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DataFormatError(f"{path}: value {key!r} = {v!r} is not a finite number")
    return doc


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
    doc = load_checkpoint(path)
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
