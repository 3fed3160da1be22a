"""Robust kernels as iteratively re-weighted least squares (IRLS) weights.

For a residual magnitude ``r >= 0`` and scale ``k > 0`` each kernel ``rho`` gives the IRLS
weight ``w(r) = rho'(r) / r``, so that minimising ``sum w_m r_m^2`` with the weights frozen and
re-weighting converges to a minimiser of ``sum rho(r_m)``:

* ``L2``:            ``w = 1``
* ``HUBER``:         ``w = 1`` for ``r <= k``, else ``k / r``
* ``CAUCHY``:        ``w = 1 / (1 + (r/k)^2)``
* ``GEMAN_MCCLURE``: ``w = 1 / (1 + (r/k)^2)^2``
* ``TUKEY``:         ``w = (1 - (r/k)^2)^2`` for ``r < k``, else 0
"""

from __future__ import annotations

import enum

import torch
from torch import Tensor

from ..errors import ConfigError, check_float, parse_choice

__all__ = ["MAD_TO_SIGMA", "RobustKernel", "robust_weight", "robust_cost"]

# 1.4826 times the median absolute value estimates a Gaussian's standard deviation (robust scales).
MAD_TO_SIGMA = 1.4826


class RobustKernel(enum.Enum):
    """Robust loss applied to a residual magnitude."""

    L2 = "l2"
    HUBER = "huber"
    CAUCHY = "cauchy"
    GEMAN_MCCLURE = "geman_mcclure"
    TUKEY = "tukey"

    @classmethod
    def parse(cls, value: "RobustKernel | str | None") -> "RobustKernel":
        """Return the member for ``value`` (``None`` means ``L2``); a bad name lists the valid ones."""
        if value is None:
            return cls.L2
        return parse_choice(cls, value, "robust kernel")


def robust_weight(r: Tensor, kernel: RobustKernel | str, scale: float | Tensor) -> Tensor:
    """Return IRLS weights ``rho'(r) / r`` for residual magnitudes.

    Args:
        r: (...) non-negative residual magnitudes (e.g. metres).
        kernel: a :class:`RobustKernel` or its name.
        scale: the kernel's scale ``k`` in the units of ``r`` (float or tensor broadcastable
            to ``r``; a tensor may require grad).

    Returns:
        (...) weights in [0, 1], same dtype as ``r``; differentiable in ``r`` and ``scale``.
    """
    check_float(r, "r")
    kernel = RobustKernel.parse(kernel)
    if isinstance(scale, (int, float)) and not scale > 0:
        raise ConfigError(f"scale: expected a positive robust scale, got {scale}")
    u2 = (r / scale) ** 2
    if kernel is RobustKernel.L2:
        return torch.ones_like(r)
    if kernel is RobustKernel.HUBER:
        # safe divisor before dividing: inside the quadratic zone the weight is 1 anyway
        big = u2 > 1
        u = torch.where(big, u2, torch.ones_like(u2)).sqrt()
        return torch.where(big, 1 / u, torch.ones_like(r))
    if kernel is RobustKernel.CAUCHY:
        return 1 / (1 + u2)
    if kernel is RobustKernel.GEMAN_MCCLURE:
        return 1 / (1 + u2) ** 2
    return torch.where(u2 < 1, (1 - u2) ** 2, torch.zeros_like(r))


def robust_cost(r: Tensor, kernel: RobustKernel | str, scale: float | Tensor) -> Tensor:
    """Return ``rho(r)``, normalised so that ``rho(r) ~ r^2 / 2`` for small ``r``.

    Args:
        r: (...) non-negative residual magnitudes.
        kernel: a :class:`RobustKernel` or its name.
        scale: the kernel's scale ``k``.

    Returns:
        (...) robust costs.
    """
    check_float(r, "r")
    kernel = RobustKernel.parse(kernel)
    k2 = torch.as_tensor(scale, dtype=r.dtype, device=r.device) ** 2
    u2 = r**2 / k2
    if kernel is RobustKernel.L2:
        return 0.5 * r**2
    if kernel is RobustKernel.HUBER:
        ar = r.abs()
        k = k2.sqrt()
        return torch.where(ar <= k, 0.5 * r**2, k * (ar - 0.5 * k))
    if kernel is RobustKernel.CAUCHY:
        return 0.5 * k2 * torch.log1p(u2)
    if kernel is RobustKernel.GEMAN_MCCLURE:
        return 0.5 * k2 * u2 / (1 + u2)
    return torch.where(u2 < 1, k2 / 6 * (1 - (1 - u2) ** 3), k2 / 6 * torch.ones_like(r))
