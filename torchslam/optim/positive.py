"""Positive values held in log space for gradient-based learning.

A value that must stay positive (a kernel width σ, a regulariser λ, a soft arg-max temperature)
is learned as ``θ = log(value)`` and used as ``exp(θ)``: any step an optimiser takes on ``θ``
leaves the value positive, and a step is relative to the value's size rather than absolute.
``torchslam.learn.learnable`` and ``torchslam.kcc.KernelCorrelator`` both hold their learnable
positive values this way.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ..errors import ConfigError

__all__ = ["positive_parameter", "positive_value"]


def positive_parameter(value: float, name: str, dtype: torch.dtype = torch.float64) -> nn.Parameter:
    """Return the 0-d parameter ``log(value)`` that :func:`positive_value` maps back to ``value``.

    Args:
        value: the initial value, a finite number > 0.
        name: what the value is, for the error message.
        dtype: floating dtype of the parameter.

    Raises:
        ConfigError: ``value`` is not a finite positive number.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}: a value learned in log space must be a finite number > 0, got {value!r}")
    return nn.Parameter(torch.tensor(math.log(value), dtype=dtype))


def positive_value(raw: Tensor) -> Tensor:
    """Return the positive value ``exp(raw)`` of a :func:`positive_parameter` (differentiable)."""
    return raw.exp()
