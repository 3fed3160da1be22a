"""Messages between a run's processes, their CPU tensors pickled as NumPy arrays.

``pickle`` writes a torch tensor through ``torch.save`` of its storage into a byte buffer and
reads it back through ``torch.load``: about 0.05 ms each way for a 4 x 4 pose, and 5 ms out and
7 ms in for a GC-SLAM keyframe's event (its ORB features, working images and pair statistics,
17 tensors). The optimisation process answers every keyframe with all the keyframe poses, so
that cost grew with the map. A NumPy array pickles as its raw bytes: the same event takes 0.4 ms
out and 0.2 ms in. :func:`dumps` sends every plain CPU tensor (no autograd, a dtype NumPy has)
that way; :func:`loads` gives each back as a tensor of its own memory with the same values,
dtype and shape. Anything else is pickled as ``pickle`` would.
"""

from __future__ import annotations

import io
import pickle
from typing import Any

import torch

__all__ = ["dumps", "loads"]


def _tensor(array) -> torch.Tensor:
    return torch.from_numpy(array)


class _Pickler(pickle.Pickler):
    def reducer_override(self, obj: Any):
        if type(obj) is not torch.Tensor or obj.device.type != "cpu" or obj.requires_grad or obj.is_sparse:
            return NotImplemented
        try:
            array = obj.detach().resolve_conj().resolve_neg().numpy()
        except (TypeError, RuntimeError):  # a dtype NumPy has not (bfloat16, ...): as pickle would
            return NotImplemented
        return _tensor, (array,)


def dumps(obj: Any) -> bytes:
    """``obj`` pickled, its plain CPU tensors as NumPy arrays."""
    out = io.BytesIO()
    _Pickler(out, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return out.getvalue()


def loads(data: bytes) -> Any:
    """What :func:`dumps` pickled (any pickle)."""
    return pickle.loads(data)
