"""Where a tensor lives, for the few decisions that depend on it."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["is_host"]

_HOST = torch.device("cpu")


def is_host(x: Tensor) -> bool:
    """Whether ``x`` lives in host memory, where reading a value back costs no synchronisation.

    Only the plain ``cpu`` device counts: an accelerator's tensors, and the stand-in device of
    ``diagnostics.device_audit`` (``cpu:0``), do not.
    """
    return x.device == _HOST
