"""A simulated accelerator on the CPU: which tensors would live on the device, what waits for it.

On a CPU-only machine every tensor is a CPU tensor, so the questions that matter on a GPU (does
this step wait for the device? does a device tensor meet a host tensor?) cannot be asked of the
tensors' ``device``. ``device_audit`` answers them with a stand-in device, ``DEVICE`` =
``cpu:0`` (plain ``cpu`` is the host):

- A tensor created on ``DEVICE`` (a factory given ``device=DEVICE``), moved there
  (``.to(DEVICE)``), marked with ``on_device``, or computed from such tensors is *device data*;
  its ``.device`` reads ``cpu:0``, so code that follows its inputs' device (``x.new_zeros``,
  ``device=x.device``) keeps its buffers there, exactly as on CUDA. Give a system
  ``device=DEVICE`` and feed it host frames: what it moves to its device is device data.
- A **synchronisation** is an operation that, were the device data on CUDA, would make the host
  wait for the device: a scalar or list read back (``item``, ``tolist``, ``bool``/``int``/
  ``float`` of a tensor, an ``if`` on one), a copy to the host (``cpu``, ``numpy``, ``.to`` a
  host device), and the operations whose output size depends on the data (``nonzero``,
  ``unique``, ``masked_select``, boolean-mask indexing, ``repeat_interleave`` without
  ``output_size``, one-argument ``torch.where``), and those that check their result on the host
  (``torch.linalg.cholesky``, ``inv``, ``solve``, ``equal``, ``allclose``). Each is recorded with
  the torchslam source line that asked for it.
- A **device mix** is an operation that takes device data and a non-scalar host tensor together,
  which raises on CUDA ("expected all tensors to be on the same device"); indexing with host
  indices and copies between the two (``to``, ``copy_``, assignment) are legal on CUDA and not
  recorded.

Limits: the values are computed on the CPU as usual (the audit changes no result), and an
operation is seen only where it goes through torch's Python layer (every tensor function and
method does).

Example:
    >>> with device_audit() as audit:
    ...     x = torch.ones(3, device=DEVICE)
    ...     _ = (x * 2).sum().item()
    >>> len(audit.syncs)
    1
"""

from __future__ import annotations

import threading
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

__all__ = ["DEVICE", "DeviceAudit", "Event", "device_audit", "is_on_device", "on_device"]

# The stand-in accelerator: a CPU device with an index, told apart from the host's plain "cpu".
DEVICE = torch.device("cpu", 0)

_ROOT = str(Path(__file__).resolve().parents[1])  # the torchslam package

_SYNC = {
    Tensor.item, Tensor.tolist, Tensor.cpu, Tensor.numpy, Tensor.__bool__, Tensor.__int__,
    Tensor.__float__, Tensor.__index__, Tensor.__format__, Tensor.__repr__, Tensor.nonzero, torch.nonzero,
    torch.argwhere, Tensor.argwhere, torch.unique, Tensor.unique, torch.unique_consecutive,
    Tensor.unique_consecutive, torch.masked_select, Tensor.masked_select, torch.equal, Tensor.equal,
    torch.allclose, Tensor.allclose, torch.linalg.cholesky, torch.linalg.inv, torch.linalg.solve,
    torch.inverse, Tensor.inverse, torch.cholesky_inverse,
}
_TO_HOST = {Tensor.item, Tensor.tolist, Tensor.cpu, Tensor.numpy}
# Legal between a device tensor and a host one on CUDA.
_MIX_OK = {Tensor.to, Tensor.copy_, Tensor.__getitem__, Tensor.__setitem__, Tensor.index_put_, Tensor.index_put}
_FACTORIES = {
    torch.zeros, torch.ones, torch.empty, torch.full, torch.arange, torch.linspace, torch.logspace,
    torch.eye, torch.tensor, torch.as_tensor, torch.rand, torch.randn, torch.randint, torch.randperm,
    torch.empty_strided, torch.tril_indices, torch.triu_indices, torch.fft.fftfreq, torch.fft.rfftfreq,
    torch.hann_window, torch.hamming_window,
}


@dataclass(frozen=True)
class Event:
    """One recorded operation: its name and the torchslam source line (``path:line``) that ran it."""

    op: str
    where: str


@dataclass
class DeviceAudit:
    """What ran on marked (device) data inside ``device_audit``.

    Attributes:
        syncs: operations that would wait for the device.
        mixed: operations that would mix device and host tensors.
    """

    syncs: list[Event] = field(default_factory=list)
    mixed: list[Event] = field(default_factory=list)

    def clear(self) -> None:
        """Forget what was recorded so far (e.g. after a warm-up step)."""
        self.syncs.clear()
        self.mixed.clear()

    def summary(self) -> dict[str, int]:
        """Counts per ``"op at path:line"``, most frequent first."""
        counts: dict[str, int] = {}
        for e in self.syncs:
            key = f"{e.op} at {e.where}"
            counts[key] = counts.get(key, 0) + 1
        return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


_state = threading.local()


def _current() -> DeviceAudit | None:
    return getattr(_state, "audit", None)


def _where() -> str:
    for frame in reversed(traceback.extract_stack()):
        f = frame.filename
        if f.startswith(_ROOT) and not f.endswith("device_audit.py"):
            return f"{Path(f).relative_to(Path(_ROOT).parent)}:{frame.lineno}"
    return "?"


def _name(func) -> str:
    return getattr(func, "__qualname__", None) or getattr(func, "__name__", repr(func))


def _bool_index(args) -> bool:
    idx = args[1] if len(args) > 1 else None
    items = idx if isinstance(idx, tuple) else (idx,)
    return any(isinstance(i, Tensor) and i.dtype == torch.bool and i.dim() > 0 for i in items)


class _OnDevice(Tensor):
    """A tensor that stands for device data (``on_device``); its results are marked too."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if getattr(func, "__self__", None) is _DEVICE_PROPERTY:  # ``x.device``
            return DEVICE
        to_host = func in _TO_HOST or (func is Tensor.to and _to_host(args, kwargs))
        audit = _current()
        if audit is not None:
            _inspect(audit, func, args, kwargs, to_host)
        with torch._C.DisableTorchFunctionSubclass():
            out = func(*args, **kwargs)
        if to_host:  # a host copy (``cpu()`` of a CPU tensor returns the tensor itself: unmark it)
            return out.as_subclass(Tensor) if isinstance(out, cls) else out
        return torch._tensor._convert(out, cls)


_DEVICE_PROPERTY = Tensor.device


def _target(args, kwargs) -> torch.device | None:
    """The device a ``Tensor.to(*args, **kwargs)`` call moves to, or None (same device)."""
    kwargs = {k: v for k, v in kwargs.items() if k != "copy"}  # ``copy=`` is ``to``'s own, not a target
    try:
        return torch._C._nn._parse_to(*args[1:], **kwargs)[0]
    except (TypeError, RuntimeError):
        return None


def _to_host(args, kwargs) -> bool:
    dev = _target(args, kwargs)
    return dev is not None and dev != DEVICE


def _inspect(audit: DeviceAudit, func, args, kwargs, to_host: bool) -> None:
    tensors = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, Tensor)]
    marked = any(isinstance(t, _OnDevice) for t in tensors)
    if not marked:
        return
    sync = func in _SYNC or to_host
    if func in (Tensor.__getitem__, Tensor.__setitem__) and _bool_index(args):
        sync = True
    elif func in (torch.repeat_interleave, Tensor.repeat_interleave):
        sync = "output_size" not in kwargs and any(isinstance(a, Tensor) for a in args[1:2])
    elif func is torch.where:
        sync = len(args) + len(kwargs) == 1
    if sync:
        audit.syncs.append(Event(_name(func), _where()))
    if func not in _MIX_OK and func not in _SYNC and any(not isinstance(t, _OnDevice) and t.dim() > 0 for t in tensors):
        audit.mixed.append(Event(_name(func), _where()))


def _is_device(device) -> bool:
    try:
        return device is not None and torch.device(device) == DEVICE
    except (TypeError, RuntimeError):
        return False


class _Placement(TorchFunctionMode):
    """Marks what a factory creates on ``DEVICE`` and what ``.to`` moves there."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        if not isinstance(out, Tensor) or isinstance(out, _OnDevice):
            return out
        if func in _FACTORIES and _is_device(kwargs.get("device")):
            return out.as_subclass(_OnDevice)
        if func is Tensor.to and _is_device(_target(args, kwargs)):
            return out.as_subclass(_OnDevice)
        return out


def on_device(x):
    """Mark a tensor (or every tensor of a list, tuple, dict or frozen dataclass) as device data (as if on ``DEVICE``).

    Returns:
        The same data, marked (a view of each tensor; nothing is copied). Outside
        ``device_audit`` the marks are inert.
    """
    import dataclasses

    if isinstance(x, Tensor):
        return x if isinstance(x, _OnDevice) else x.as_subclass(_OnDevice)
    if isinstance(x, (list, tuple)):
        return type(x)(on_device(v) for v in x)
    if isinstance(x, dict):
        return {k: on_device(v) for k, v in x.items()}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        changes = {f.name: on_device(getattr(x, f.name)) for f in dataclasses.fields(x) if f.init}
        return dataclasses.replace(x, **changes)
    return x


def is_on_device(x: Tensor) -> bool:
    """Whether ``x`` is marked device data (``on_device`` or derived from it)."""
    return isinstance(x, _OnDevice)


@contextmanager
def device_audit():
    """Record the synchronisations and device mixes of marked data (module docstring).

    Yields:
        DeviceAudit, filled as the block runs. Audits do not nest: an inner one records alone.
    """
    audit = DeviceAudit()
    outer = _current()
    _state.audit = audit
    try:
        with _Placement():
            yield audit
    finally:
        _state.audit = outer
