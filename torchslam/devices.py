"""Where a tensor lives, for the few decisions that depend on it, and the host's faster gathers.

Single-threaded torch on a CPU is several times slower than NumPy at a few irregular operations
that sparse registration runs on long index lists (row gathers, run-length repeats, the indices
of a mask). ``index_select``, ``repeat_counts`` and ``flat_nonzero`` give torch's result through
NumPy for host tensors and run the torch operation elsewhere (queued on the device, no
synchronisation beyond torch's own).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["flat_nonzero", "index_select", "is_host", "numpy_viewable", "repeat_counts"]

_HOST = torch.device("cpu")


def is_host(x: Tensor) -> bool:
    """Whether ``x`` lives in host memory, where reading a value back costs no synchronisation.

    Only the plain ``cpu`` device counts: an accelerator's tensors, and the stand-in device of
    ``diagnostics.device_audit`` (``cpu:0``), do not.
    """
    return x.device == _HOST


def numpy_viewable(x: Tensor) -> bool:
    """Whether a NumPy fast path may stand in for torch on ``x``: a plain host tensor (not the
    marked subclass of ``diagnostics.device_audit``'s stand-in device) that needs no gradient."""
    return is_host(x) and type(x) is Tensor and not x.requires_grad


def index_select(x: Tensor, dim: int, index: Tensor) -> Tensor:
    """``torch.index_select(x, dim, index)`` with a (K,) int64 ``index``.

    On the host through ``numpy.take`` (about five times faster for rows of a few numbers, one
    thread).
    """
    if numpy_viewable(x) and numpy_viewable(index) and x.dtype != torch.bool:
        return torch.from_numpy(np.take(x.numpy(), index.numpy(), axis=dim))
    return x.index_select(dim, index)


def repeat_counts(values: Tensor, counts: Tensor) -> Tensor:
    """``torch.repeat_interleave(values, counts)`` of (N,) tensors: ``values[n]`` ``counts[n]`` times."""
    if numpy_viewable(values) and numpy_viewable(counts):
        return torch.from_numpy(np.repeat(values.numpy(), counts.numpy()))
    return torch.repeat_interleave(values, counts)


def flat_nonzero(mask: Tensor) -> Tensor:
    """(K,) int64 indices of the True entries of a 1-D bool ``mask``, ascending."""
    if numpy_viewable(mask):
        return torch.from_numpy(np.flatnonzero(mask.numpy()).astype(np.int64, copy=False))
    return mask.nonzero().squeeze(-1)
