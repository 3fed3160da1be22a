"""Correlation peaks: integer arg-max with signed wrap-around, quadratic sub-pixel refinement,
soft arg-max, peak-to-sidelobe ratio and the shift variance (NI-SLAM Eq. (17), (19), (22)).

Pure, batched functions over (B, H, W) correlation outputs in the spatial domain. The Fourier
sub-pixel refinement works on the response's spectrum and stays with the correlator
(``correlator.find_peak``), which dispatches between the two refinements.

Convention:
    Peaks are reported as ``(col, row)`` = ``(x, y)``, wrapped to the signed range
    ``[-⌊n/2⌋, ⌈n/2⌉ - 1]`` (see ``correlator``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ConfigError, ShapeError, check_float, check_shape

__all__ = ["Peak", "peak_to_sidelobe", "shift_variance", "soft_argmax"]


def _per_item(value, ref: Tensor, name: str) -> Tensor:
    """A float or a 0-d / (B,) tensor as a (B or 1, 1, 1) tensor in ``ref``'s dtype and device."""
    t = torch.as_tensor(value, dtype=ref.dtype, device=ref.device)
    if t.dim() == 0:
        return t.reshape(1, 1, 1)
    if t.dim() == 1 and t.shape[0] in (1, ref.shape[0]):
        return t.reshape(-1, 1, 1)
    raise ShapeError(f"{name}: expected a scalar or shape ({ref.shape[0]},), got {tuple(t.shape)}")


def _wrap(i: Tensor, n: int) -> Tensor:
    """Wrap indices to the signed range [-n//2, n - n//2 - 1]."""
    return torch.remainder(i + n // 2, n) - n // 2


def _check_response(g: Tensor, name: str = "response") -> None:
    check_shape(g, "B H W", name)
    check_float(g, name)



@dataclass(frozen=True)
class Peak:
    """Location of the correlation peak.

    Attributes:
        index: (B, 2) long integer arg-max ``(col, row)``, wrapped to signed shifts.
        shift: (B, 2) refined shift ``(s_x, s_y)`` in pixels (equal to ``index`` where
            refinement is off or failed).
        value: (B,) correlation output at the integer peak.
        refined: (B,) bool, True where sub-pixel refinement converged inside ±1 px.
    """

    index: Tensor
    shift: Tensor
    value: Tensor
    refined: Tensor


def _argmax(g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Integer arg-max rows, cols (unwrapped, (B,)) and the peak values."""
    B, H, W = g.shape
    value, flat = g.reshape(B, H * W).max(dim=1)
    return flat // W, flat % W, value


def _refine_quadratic(g: Tensor, row: Tensor, col: Tensor) -> tuple[Tensor, Tensor]:
    B, H, W = g.shape
    off = torch.arange(-1, 2, device=g.device)
    rr = torch.remainder(row[:, None, None] + off[None, :, None], H)
    cc = torch.remainder(col[:, None, None] + off[None, None, :], W)
    f = g.reshape(B, H * W).gather(1, (rr * W + cc).reshape(B, 9)).reshape(B, 3, 3)  # [dy + 1, dx + 1]
    # Least-squares fit of a + b·d + d_xx dx² + d_yy dy² + d_xy dx dy on the 3x3 stencil. The odd
    # terms are orthogonal to the rest; solving the 3x3 normal equations of {1, dx², dy²} gives
    # d_xx = Σ f dx² / 2 - Σ f / 3 (and likewise d_yy).
    d = torch.arange(-1, 2, dtype=g.dtype, device=g.device)
    sx, sy = (f * d).sum(dim=(1, 2)), (f * d[:, None]).sum(dim=(1, 2))
    sxx, syy = (f * d.square()).sum(dim=(1, 2)), (f * d.square()[:, None]).sum(dim=(1, 2))
    sxy, total = (f * (d[:, None] * d)).sum(dim=(1, 2)), f.sum(dim=(1, 2))
    bx, by = sx / 6, sy / 6
    dxx, dyy, dxy = sxx / 2 - total / 3, syy / 2 - total / 3, sxy / 4
    # Stationary point of b·d + d^T [[dxx, dxy/2],[dxy/2, dyy]] d.
    hxx, hyy, hxy = 2 * dxx, 2 * dyy, dxy
    det = hxx * hyy - hxy * hxy
    ok = (hxx < 0) & (det > 0)
    det = torch.where(ok, det, torch.ones_like(det))
    ox = -(hyy * bx - hxy * by) / det
    oy = -(-hxy * bx + hxx * by) / det
    ok = ok & (ox.abs() <= 1) & (oy.abs() <= 1)
    off_xy = torch.stack([ox, oy], dim=1)
    return torch.where(ok[:, None], off_xy, torch.zeros_like(off_xy)), ok


def soft_argmax(g: Tensor, temperature) -> Tensor:
    """Differentiable shift estimate: the softmax(g / T)-weighted mean of signed offsets.

    Offsets are taken relative to the hard peak and wrapped, so a peak near the image border is
    not averaged across the wrap-around; the integer hard peak carries no gradient and the
    softmax part is differentiable in ``g`` (hence in σ, λ and the images) and in ``temperature``.

    Args:
        g: (B, H, W) correlation output.
        temperature: a float or 0-d / (B,) tensor > 0, in units of ``g``.

    Returns:
        (B, 2) shift ``(s_x, s_y)`` in pixels.
    """
    _check_response(g, "g")
    B, H, W = g.shape
    T = _per_item(temperature, g, "temperature")
    row, col, _ = _argmax(g.detach())
    dy = _wrap(torch.arange(H, device=g.device)[None, :] - row[:, None], H).to(g.dtype)  # (B, H)
    dx = _wrap(torch.arange(W, device=g.device)[None, :] - col[:, None], W).to(g.dtype)  # (B, W)
    p = torch.softmax((g / T).reshape(B, H * W), dim=1).reshape(B, H, W)
    ox = (p.sum(dim=1) * dx).sum(dim=1)
    oy = (p.sum(dim=2) * dy).sum(dim=1)
    base = torch.stack([_wrap(col, W), _wrap(row, H)], dim=1).to(g.dtype)
    return base + torch.stack([ox, oy], dim=1)


def peak_to_sidelobe(g: Tensor, index: Tensor | None = None, window: int = 11, eps: float = 1e-12) -> Tensor:
    """Peak-to-sidelobe ratio ``(max g - μ_s) / σ_s`` (NI-SLAM Eq. (22)).

    The sidelobe is every pixel outside a ``window x window`` square centred on the peak,
    with wrap-around (the output is circular). ``σ_s`` is the population standard deviation;
    a flat sidelobe (``σ_s = 0``) is guarded by ``eps`` and gives a very large PSR.

    Args:
        g: (B, H, W) correlation output.
        index: (B, 2) peak ``(col, row)`` (signed or not); ``None`` = the arg-max of ``g``.
        window: odd side of the excluded square, pixels.
        eps: lower bound on ``σ_s``.

    Returns:
        (B,) PSR.
    """
    _check_response(g, "g")
    B, H, W = g.shape
    if not (isinstance(window, int) and window >= 1 and window % 2 == 1):
        raise ConfigError(f"window: expected a positive odd integer, got {window!r}")
    if window >= H or window >= W:
        raise ConfigError(f"window: {window} leaves no sidelobe in a ({H}, {W}) response")
    if index is None:
        row, col, _ = _argmax(g.detach())
    else:
        check_shape(index, f"{B} 2", "index")
        col, row = torch.remainder(index[:, 0].long(), W), torch.remainder(index[:, 1].long(), H)
    half = window // 2
    dy = _wrap(torch.arange(H, device=g.device)[None, :] - row[:, None], H).abs() > half  # (B, H)
    dx = _wrap(torch.arange(W, device=g.device)[None, :] - col[:, None], W).abs() > half  # (B, W)
    side = (dy[:, :, None] | dx[:, None, :]).to(g.dtype)  # (B, H, W)
    n = side.sum(dim=(1, 2))
    peak = g.reshape(B, H * W).gather(1, (row * W + col)[:, None])[:, 0]
    mu = (g * side).sum(dim=(1, 2)) / n
    if torch.is_grad_enabled() and g.requires_grad:
        var = ((g - mu[:, None, None]).square() * side).sum(dim=(1, 2)) / n
    else:  # the same products in place on the fresh deviations
        var = (g - mu[:, None, None]).square_().mul_(side).sum(dim=(1, 2)) / n
    return (peak - mu) / var.clamp_min(eps * eps).sqrt()


def shift_variance(g: Tensor, peak_value: Tensor | None = None, resolution: Tensor | None = None) -> Tensor:
    """Per-axis variance of the estimated translation ``r² Σg / (2π max g)`` (NI-SLAM Eq. (19)).

    With ``ĝ = 1``, ``Σg = κ̂_z(x)[0] / (κ̂_z(z)[0] + λ)`` is a ratio of sums of positive kernel
    values, so it is positive, and so is ``max g`` (at least the mean), unless every kernel
    value underflows (a frame that shares nothing with the keyframe, in float32 when the mean
    squared difference exceeds ~87 σ²): then ``g = 0`` and the variance is reported as ``inf``.

    Args:
        g: (B, H, W) correlation output.
        peak_value: (B,) value at the peak; ``None`` = ``g.max()``.
        resolution: (B,) metres per pixel; ``None`` gives the variance in pixels².

    Returns:
        (B,) variance, m² (or px²), the same for x and y.
    """
    _check_response(g, "g")
    B = g.shape[0]
    if peak_value is None:
        peak_value = g.reshape(B, -1).amax(dim=1)
    total = g.sum(dim=(1, 2))
    good = (peak_value > 0) & (total > 0)
    safe_peak = torch.where(good, peak_value, torch.ones_like(peak_value))
    var = torch.where(good, total / (2 * math.pi * safe_peak), math.inf)
    if resolution is not None:
        check_shape(resolution, f"{B}", "resolution")
        var = var * resolution.to(g.dtype).square()
    return var
