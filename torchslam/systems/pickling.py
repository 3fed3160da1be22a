"""Messages between a run's processes, their CPU tensors pickled as NumPy arrays.

``pickle`` writes a torch tensor through ``torch.save`` of its storage into a byte buffer and
reads it back through ``torch.load``, about 0.05 ms each way for a 4 x 4 pose. In a GC-SLAM run
on TUM fr1/xyz a keyframe's event (its ORB features, working images and pair statistics) took
1.5 ms out and 2.2 ms in, and the optimisation process answers every keyframe with all the
keyframe poses, so that answer grew with the map: 5.5 ms out and 7.3 ms in at 150 keyframes. A
NumPy array pickles as its raw bytes: 0.36 / 0.30 ms for the event, 0.76 / 0.32 ms for 150
poses. :func:`dumps` sends every plain CPU tensor (no autograd, a dtype NumPy has)
that way; :func:`loads` gives each back as a tensor of its own memory with the same values,
dtype and shape. Anything else is pickled as ``pickle`` would.
"""

from __future__ import annotations

import io
import pickle
from typing import Any

import torch

__all__ = ["dumps", "loads"]


class _Pickler(pickle.Pickler):
    def reducer_override(self, obj: Any):
        if type(obj) is not torch.Tensor or obj.device.type != "cpu" or obj.requires_grad or obj.is_sparse:
            return NotImplemented
        try:
            array = obj.detach().resolve_conj().resolve_neg().numpy()
        except (TypeError, RuntimeError):  # a dtype NumPy has not (bfloat16, ...): as pickle would
            return NotImplemented
        return torch.from_numpy, (array,)


def dumps(obj: Any) -> bytes:
    """``obj`` pickled, its plain CPU tensors as NumPy arrays."""
    out = io.BytesIO()
    _Pickler(out, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return out.getvalue()


def loads(data: bytes) -> Any:
    """What :func:`dumps` pickled (any pickle)."""
    return pickle.loads(data)
