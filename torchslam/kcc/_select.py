"""Element-wise selection that is fast on CPU: ``torch.where`` computed bitwise.

On the CPU build torchslam uses, ``torch.where`` over a bool mask is not vectorised, while the
same selection done with integer bit operations on the values' bit patterns is. The NI-SLAM
front-end selects about a dozen full-resolution arrays per frame, so the difference shows in the
per-frame time. The bitwise form gives bit-identical results (it moves bit patterns, it does no
arithmetic), including NaN, inf and signed zeros.

It falls back to ``torch.where`` where it would not help or not be valid: off the CPU (GPU
``where`` is already a vectorised kernel), when autograd has to see the selection, and for
dtypes or mixed-dtype operands the bit trick does not cover.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import broadcast_shape

_BITS = {
    torch.float32: torch.int32,
    torch.float64: torch.int64,
    torch.int32: torch.int32,
    torch.int64: torch.int64,
}


def where(mask: Tensor, a: Tensor, b: Tensor | float) -> Tensor:
    """``torch.where(mask, a, b)`` (with broadcasting), bit for bit.

    Args:
        mask: bool tensor broadcastable with ``a``.
        a: values where ``mask`` is True.
        b: values where it is False: a tensor of ``a``'s dtype, or a Python number.

    Returns:
        The selection, in ``a``'s dtype.
    """
    bits = _BITS.get(a.dtype)
    scalar = not isinstance(b, Tensor)
    if (
        bits is None
        or a.device.type != "cpu"
        or mask.dtype != torch.bool
        or (not scalar and (b.dtype != a.dtype or b.device != a.device))
        or (torch.is_grad_enabled() and (a.requires_grad or (not scalar and b.requires_grad)))
    ):
        return torch.where(mask, a, b)
    # An integer product with the mask (promoted to 0 or 1 inside the kernel) keeps a bit pattern
    # or clears it, without first converting the mask to a full-width all-ones pattern.
    a_bits = a.view(bits)
    if scalar and b == 0 and math.copysign(1.0, b) > 0:
        return (a_bits * mask).view(a.dtype)  # +0 has no bits set
    b_bits = (a.new_full((), b) if scalar else b).view(bits)
    diff = a_bits ^ b_bits  # a fresh tensor: the rest in place where the mask's shape fits in it
    if broadcast_shape(diff.shape, mask.shape, what="the values and the mask") == diff.shape:
        diff.mul_(mask)
    else:
        diff = diff * mask
    diff ^= b_bits
    return diff.view(a.dtype)
