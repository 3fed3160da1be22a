"""Errors raised by torchslam and the shape checker used at public boundaries."""

from __future__ import annotations

from collections.abc import MutableMapping

import torch

__all__ = ["TorchSlamError", "ShapeError", "DataFormatError", "ConfigError", "DTypeError", "check_shape", "check_float", "parse_choice"]


class TorchSlamError(Exception):
    """Base class of every error torchslam raises on purpose."""


class ShapeError(TorchSlamError, ValueError):
    """A tensor argument has the wrong shape."""


class DataFormatError(TorchSlamError, ValueError):
    """A file or folder does not hold what it should; the message names the file and line."""


class DTypeError(TorchSlamError, TypeError):
    """A tensor argument has an unsupported dtype (only float32 and float64 are accepted)."""


class ConfigError(TorchSlamError, ValueError):
    """A configuration key or value is invalid; the message names the key."""


def _fmt(shape) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def check_shape(x, spec: str, name: str, dims: MutableMapping[str, int] | None = None) -> None:
    """Check that ``x`` is a tensor whose shape matches ``spec``.

    ``spec`` is a space-separated list of dimension names or integers, optionally starting with
    ``...`` for any number of leading dimensions, e.g. ``"... N 3"`` or ``"B 4 4"``. Names are
    bound in ``dims`` on first sight, so later calls with the same ``dims`` check arguments
    against each other.

    Args:
        x: the value to check.
        spec: expected shape.
        name: argument name used in the message.
        dims: optional mapping of already-bound dimension sizes; updated in place.

    Raises:
        ShapeError: naming the argument, the expected and the received shape.
    """
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"{name}: expected a tensor of shape ({spec.replace(' ', ', ')}), got {type(x).__name__}")
    if dims is None:
        dims = {}
    tokens = spec.split()
    ellipsis = bool(tokens) and tokens[0] == "..."
    if ellipsis:
        tokens = tokens[1:]
    shape = tuple(x.shape)
    expected = "(" + ", ".join((["..."] if ellipsis else []) + tokens) + ")"
    if (ellipsis and len(shape) < len(tokens)) or (not ellipsis and len(shape) != len(tokens)):
        raise ShapeError(f"{name}: expected {expected}, got {_fmt(shape)}")
    tail = shape[len(shape) - len(tokens):] if tokens else ()
    for tok, size in zip(tokens, tail):
        if tok.isdigit():
            if int(tok) != size:
                raise ShapeError(f"{name}: expected {expected}, got {_fmt(shape)}")
        elif tok in dims:
            if dims[tok] != size:
                raise ShapeError(
                    f"{name}: expected {expected} with {tok}={dims[tok]}, got {_fmt(shape)}"
                )
        else:
            dims[tok] = size


def check_float(x: torch.Tensor, name: str) -> None:
    """Raise DTypeError unless ``x`` is float32 or float64."""
    if x.dtype not in (torch.float32, torch.float64):
        raise DTypeError(f"{name}: expected float32 or float64, got {x.dtype}")


def parse_choice(cls, value, what: str):
    """Return the member of enum ``cls`` named by ``value`` (a member or its value, any case).

    Raises:
        ConfigError: naming ``what``, the bad value and the valid ones.
    """
    if isinstance(value, cls):
        return value
    try:
        return cls(str(value).lower())
    except ValueError:
        valid = ", ".join(m.value for m in cls)
        raise ConfigError(f"{what}: unknown {value!r}; valid: {valid}") from None
