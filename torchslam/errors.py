"""Errors raised by torchslam, the shape checker used at public boundaries and the config field limits."""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import numbers
import types
import typing
from collections.abc import MutableMapping
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch

__all__ = [
    "TorchSlamError", "ShapeError", "DataFormatError", "ConfigError", "DTypeError", "FieldError", "InvalidValueError", "Limit",
    "check_shape", "check_float", "check_increasing", "check_limits", "parse_choice", "broadcast_shape",
]


E = TypeVar("E", bound=enum.Enum)


class TorchSlamError(Exception):
    """Base class of every error torchslam raises on purpose."""


class ShapeError(TorchSlamError, ValueError):
    """A tensor argument has the wrong shape."""


class DataFormatError(TorchSlamError, ValueError):
    """A file or folder does not hold what it should; the message names the file and line."""


class InvalidValueError(TorchSlamError, ValueError):
    """A tensor argument has the right shape but invalid values (out of order, out of range)."""


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


def broadcast_shape(*shapes: tuple[int, ...], what: str = "shapes") -> tuple[int, ...]:
    """The shape that ``shapes`` broadcast to: ``numpy.broadcast_shapes``, raising ``ShapeError``.

    ``torch.broadcast_shapes`` imports ``torch.fx``'s symbolic shapes (and SymPy) on its first
    call, about 0.4 s of a run's start, and costs about 15 us a call afterwards; NumPy's rule is
    the same, on plain tuples, in about 2 us.

    Raises:
        ShapeError: the shapes do not broadcast (``what`` names them).
    """
    try:
        return tuple(np.broadcast_shapes(*shapes))
    except ValueError:
        raise ShapeError(f"{what}: {', '.join(_fmt(x) for x in shapes)} do not broadcast") from None


def check_float(x: torch.Tensor, name: str) -> None:
    """Raise DTypeError unless ``x`` is float32 or float64."""
    if x.dtype not in (torch.float32, torch.float64):
        raise DTypeError(f"{name}: expected float32 or float64, got {x.dtype}")


def check_increasing(t: torch.Tensor, name: str) -> None:
    """Raise InvalidValueError unless the (N,) timestamps ``t`` are strictly increasing."""
    if t.numel() > 1 and not bool((t[1:] > t[:-1]).all()):
        raise InvalidValueError(f"{name}: must be strictly increasing")


def parse_choice(cls: type[E], value: Any, what: str) -> E:
    """Return the member of enum ``cls`` named by ``value``: a member, its value or its name, any case.

    Every option of the library (config fields, function arguments) is parsed here, so a bad
    value reads the same everywhere: ``what: 'x' is not one of ['a', 'b']``.

    Raises:
        ConfigError: naming ``what``, the bad value and the valid values.
    """
    if isinstance(value, cls):
        return value
    if isinstance(value, str):
        text = value.strip().lower()
        for member in cls:
            if text == str(member.value).lower() or text == member.name.lower():
                return member
    else:
        for member in cls:
            if value == member.value and type(value) is not bool:
                return member
    raise ConfigError(f"{what}: {value!r} is not one of {[m.value for m in cls]}")


# --------------------------------------------------------------------------------------------
# Config field limits: one declaration per numeric field, one check for every config class.


class FieldError(ConfigError):
    """A config field holds a value outside its declared limits.

    The message is ``Owner.field: reason`` (``KCCConfig.sigma: expected ...``); config loading
    names the dotted key instead (``kcc.sigma``).

    Attributes:
        field: the field's name.
        reason: what was expected and what was received.
    """

    def __init__(self, field: str, reason: str, owner: str | None = None) -> None:
        super().__init__(f"{owner + '.' if owner else ''}{field}: {reason}")
        self.field = field
        self.reason = reason


@dataclass(frozen=True)
class Limit:
    """Allowed values of one numeric config field.

    A float field is always finite unless ``allow_inf`` (NaN is never allowed); bounds apply
    to every number of the field (each element of a tuple field). ``Limit()`` means any finite
    number, and is the declaration of a field that may be negative.

    Attributes:
        gt, ge, lt, le: strict and inclusive lower and upper bounds, or None.
        allow_inf: +inf/-inf are accepted (within the bounds); e.g. "no limit" time constants.
        odd: integers must be odd (window sides).
    """

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    allow_inf: bool = False
    odd: bool = False

    def describe(self, integer: bool) -> str:
        """The expectation in words: ``"a finite number > 0"``, ``"an odd integer >= 1"``."""
        kind = ("an odd integer" if self.odd else "an integer") if integer else (
            "a number" if self.allow_inf else "a finite number"
        )
        bounds = [f"{op} {_num(v)}" for op, v in ((">", self.gt), (">=", self.ge), ("<", self.lt), ("<=", self.le)) if v is not None]
        text = kind + (" " + " and ".join(bounds) if bounds else "")
        return text + (" (inf allowed)" if self.allow_inf and not integer else "")

    def check(self, value, integer: bool) -> str | None:
        """Return why ``value`` is not allowed, or None when it is."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return "not a number"
        if integer and not isinstance(value, numbers.Integral):
            return "not an integer"
        v = float(value)
        if math.isnan(v) or (math.isinf(v) and not self.allow_inf):
            return "not finite"
        if (
            (self.gt is not None and not v > self.gt)
            or (self.ge is not None and not v >= self.ge)
            or (self.lt is not None and not v < self.lt)
            or (self.le is not None and not v <= self.le)
            or (self.odd and int(value) % 2 != 1)
        ):
            return "out of range"
        return None


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


ANY = Limit()
POSITIVE = Limit(gt=0)
NON_NEGATIVE = Limit(ge=0)
AT_LEAST_1 = Limit(ge=1)
FRACTION = Limit(ge=0, le=1)


def _number_kind(tp) -> tuple[str, bool] | None:
    """``(shape, integer)`` of a numeric field type: shape "scalar", "optional" or "tuple"; None otherwise."""
    if tp is bool:
        return None
    if tp in (int, float):
        return "scalar", tp is int
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1 and type(None) in args:
            inner = _number_kind(rest[0])
            return ("optional", inner[1]) if inner is not None and inner[0] == "scalar" else None
        return None
    if origin is tuple and args and all(a in (int, float) or a is Ellipsis for a in args):
        return "tuple", all(a is int or a is Ellipsis for a in args)
    return None


@functools.cache
def numeric_fields(cls) -> dict[str, tuple[str, bool]]:
    """The numeric fields of config dataclass ``cls``: name -> ``(shape, integer)`` (see ``_number_kind``)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        kind = _number_kind(hints[f.name])
        if kind is not None:
            out[f.name] = kind
    return out


def check_limits(cfg) -> None:
    """Check every numeric field of the config dataclass ``cfg`` against its declared ``Limit``.

    A config class declares ``LIMITS: ClassVar[dict[str, Limit]]``, one entry per numeric
    (int, float, optional or tuple of them) field; a field without an entry is refused as a
    programming error, so a new field cannot go unchecked. Call it from ``__post_init__``.

    Raises:
        FieldError: naming the field, the expectation and the value.
        TypeError: for a numeric field without a declared limit, or a limit for no such field.
    """
    cls = type(cfg)
    limits: dict[str, Limit] = getattr(cls, "LIMITS", {})
    fields_ = numeric_fields(cls)
    missing = sorted(set(fields_) - set(limits))
    extra = sorted(set(limits) - set(fields_))
    if missing or extra:
        raise TypeError(f"{cls.__name__}.LIMITS: no limit declared for {missing}, limits for non-numeric or absent fields {extra}")
    for name, (shape, integer) in fields_.items():
        value = getattr(cfg, name)
        limit = limits[name]
        if shape == "optional" and value is None:
            continue
        if shape == "tuple":
            if not isinstance(value, (tuple, list)):
                raise FieldError(name, f"expected a list, got {value!r}", cls.__name__)
            bad = [v for v in value if limit.check(v, integer) is not None]
            if bad:
                raise FieldError(name, f"expected each value {limit.describe(integer)}, got {bad[0]!r} in {list(value)!r}", cls.__name__)
            continue
        if limit.check(value, integer) is not None:
            alternative = " or None" if shape == "optional" else ""
            raise FieldError(name, f"expected {limit.describe(integer)}{alternative}, got {value!r}", cls.__name__)
