"""Count the host-device synchronisations a region of code would make on an accelerator.

An operation synchronises the host with the device when the host needs a value or a size
that only the device knows (``.item()``, ``bool(t)``, ``nonzero``, ...), or when it copies
between pageable host memory and the device (``.cpu()``, ``t.new_tensor([...])``). Each one
drains the device's queue and idles it while Python goes on, so a loop on an accelerator is
only as fast as its number of synchronisations allows.

:func:`count_syncs` finds them on any device, the CPU included, where they cost nothing and
are otherwise invisible: it records every operation that *would* synchronise if its inputs
were on a CUDA device. Two interposition layers are used together:

* a :class:`~torch.overrides.TorchFunctionMode` sees the Python-level calls: ``Tensor.item``,
  ``tolist``, ``numpy``, ``__array__``, ``cpu``, ``cuda``, ``to`` a CPU device,
  ``__bool__`` / ``__int__`` / ``__float__`` / ``__index__`` / ``__complex__`` (``if t:``,
  ``int(t)``, ``range(t)``), printing a tensor, and host data put on a device
  (``Tensor.new_tensor``, ``torch.tensor`` / ``torch.as_tensor`` of host data with a ``device``);
* a :class:`~torch.utils._python_dispatch.TorchDispatchMode` sees the ATen operators that the
  Python level cannot name, wherever they are called from: ``nonzero`` (``torch.where(c)``,
  ``argwhere``), ``_unique2`` and friends, ``masked_select``, ``index`` / ``index_put_`` with a
  boolean mask, ``repeat_interleave`` without ``output_size``, ``bincount``, ``equal``,
  ``_linalg_check_errors`` (the error check of ``torch.linalg.cholesky``, ``inv``, ``solve``),
  and ``_local_scalar_dense`` reached from C++ (a 0-dim tensor passed as a Python number).

An operation recorded at the Python level is not recorded again for the ATen operators it runs
(``.item()`` dispatches ``_local_scalar_dense``), and reading a host copy right after making it
(``x.cpu().numpy()``, ``np.asarray(x.cpu())``) is part of that copy, so every synchronisation
counts once.

Conventions and limits:
    ``.to(device)`` counts when its target is the CPU and either the tensor is elsewhere or the
    target was written as a string (``.to("cpu")``): on a CPU run ``t.to(x.device)`` with ``x``
    on the CPU is a no-op that stays one on an accelerator, so it does not count. Likewise
    ``torch.tensor(data)`` without a ``device`` builds a host tensor and does not count.
    ``t[mask] = scalar`` runs ``masked_fill_`` on CUDA and does not count. On the CPU ``x.cpu()``
    returns ``x`` itself, so ``x.cpu()`` followed at once by ``x.item()`` counts once. Operations inside
    CUDA kernels' own implementations (a cuSOLVER info check that is not an ATen operator) are
    not seen. Modes are per thread: work that another thread runs (GC-SLAM's background
    optimisation) is not counted.

Example::

    with count_syncs() as syncs:
        step(x)
    assert syncs.count <= 1, syncs.summary()
"""

from __future__ import annotations

import collections
import contextlib
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["SyncEvent", "SyncReport", "SyncKind", "count_syncs"]


class SyncKind:
    """Why an operation synchronises (the ``kind`` of a :class:`SyncEvent`)."""

    SCALAR = "scalar to host"  # item, bool(), int(), float(), _local_scalar_dense
    COPY_TO_HOST = "copy to host"  # cpu(), numpy(), tolist(), to("cpu"), printing
    COPY_TO_DEVICE = "copy to device"  # new_tensor, tensor/as_tensor of host data on a device
    SHAPE = "data-dependent shape"  # nonzero, unique, masked_select, boolean indexing, ...
    ERROR_CHECK = "error check"  # linalg functions that raise on a failed factorisation


@dataclass(frozen=True)
class SyncEvent:
    """One synchronising operation.

    Attributes:
        op: the operation, e.g. ``"Tensor.item"`` or ``"aten.nonzero (in torch.where)"``.
        kind: a :class:`SyncKind` string.
        where: ``"file:line in function"`` of the innermost caller outside torch itself.
    """

    op: str
    kind: str
    where: str


@dataclass
class SyncReport:
    """The synchronisations recorded by :func:`count_syncs`, in the order they happened.

    Attributes:
        events: every :class:`SyncEvent`.
    """

    events: list[SyncEvent] = field(default_factory=list)

    @property
    def count(self) -> int:
        """Number of synchronisations."""
        return len(self.events)

    def __len__(self) -> int:
        return len(self.events)

    def by_location(self) -> collections.Counter:
        """``Counter`` of ``(op, where)``: which call sites synchronise and how often."""
        return collections.Counter((e.op, e.where) for e in self.events)

    def summary(self) -> str:
        """One line per call site, most frequent first (for assertion messages)."""
        lines = [f"{self.count} synchronisation(s)"]
        lines += [f"  {n} x {op} at {where}" for (op, where), n in self.by_location().most_common()]
        return "\n".join(lines)


_TORCH_DIR = os.path.dirname(torch.__file__) + os.sep
_THIS_FILE = os.path.abspath(__file__)
_SKIP_FILES = (_THIS_FILE, contextlib.__file__)


def _caller() -> str:
    """``file:line in function`` of the innermost frame outside torch and this module."""
    f = sys._getframe(1)
    while f is not None:
        name = os.path.abspath(f.f_code.co_filename)
        if not name.startswith(_TORCH_DIR) and name not in _SKIP_FILES:
            return f"{_short(name)}:{f.f_lineno} in {f.f_code.co_name}"
        f = f.f_back
    return "<unknown>"


def _short(path: str) -> str:
    """The path from its ``torchslam``/``tests``/``scripts`` folder on, else the file name."""
    parts = path.split(os.sep)
    for root in ("torchslam", "tests", "scripts"):
        if root in parts:
            return "/".join(parts[len(parts) - 1 - parts[::-1].index(root):])
    return parts[-1]


T = torch.Tensor
# Python-level operations that always synchronise.
_ALWAYS = {
    T.item: ("Tensor.item", SyncKind.SCALAR),
    T.__bool__: ("Tensor.__bool__", SyncKind.SCALAR),
    T.__int__: ("Tensor.__int__", SyncKind.SCALAR),
    T.__float__: ("Tensor.__float__", SyncKind.SCALAR),
    T.__index__: ("Tensor.__index__", SyncKind.SCALAR),
    T.__complex__: ("Tensor.__complex__", SyncKind.SCALAR),
    T.tolist: ("Tensor.tolist", SyncKind.COPY_TO_HOST),
    T.numpy: ("Tensor.numpy", SyncKind.COPY_TO_HOST),
    T.__array__: ("Tensor.__array__", SyncKind.COPY_TO_HOST),
    T.cpu: ("Tensor.cpu", SyncKind.COPY_TO_HOST),
    T.__repr__: ("Tensor.__repr__", SyncKind.COPY_TO_HOST),
    T.__str__: ("Tensor.__str__", SyncKind.COPY_TO_HOST),
    T.__format__: ("Tensor.__format__", SyncKind.COPY_TO_HOST),
    T.cuda: ("Tensor.cuda", SyncKind.COPY_TO_DEVICE),
    T.new_tensor: ("Tensor.new_tensor", SyncKind.COPY_TO_DEVICE),
}


# Reads of a host tensor: no synchronisation of their own right after a copy to the host.
_READS_HOST = {T.numpy, T.__array__, T.tolist, T.item, T.__bool__, T.__int__, T.__float__, T.__index__}


def _is_cpu(device) -> bool:
    return device is not None and torch.device(device).type == "cpu"


def _python_level(func, args, kwargs) -> tuple[str, str] | None:
    """``(op, kind)`` if the Python-level call ``func(*args, **kwargs)`` synchronises."""
    hit = _ALWAYS.get(func)
    if hit is not None:
        return hit
    if func is T.to:
        device = torch._C._nn._parse_to(*args[1:], **kwargs)[0]
        if not _is_cpu(device):
            return None
        as_text = any(isinstance(a, str) for a in args[1:]) or isinstance(kwargs.get("device"), str)
        if as_text or args[0].device.type != "cpu":
            return "Tensor.to", SyncKind.COPY_TO_HOST
        return None
    if func is torch.tensor or func is torch.as_tensor:
        device = kwargs.get("device", args[2] if func is torch.as_tensor and len(args) > 2 else None)
        if device is None:
            return None
        data = args[0] if args else kwargs.get("data")
        if isinstance(data, torch.Tensor):
            if data.device.type != torch.device(device).type:
                return f"torch.{func.__name__}", SyncKind.COPY_TO_HOST if _is_cpu(device) else SyncKind.COPY_TO_DEVICE
            return None
        return f"torch.{func.__name__}", SyncKind.COPY_TO_DEVICE
    return None


def _has_bool_index(indices) -> bool:
    return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices if i is not None)


_aten = torch.ops.aten
# ATen operators that synchronise whatever their arguments.
_DISPATCH_ALWAYS = {
    _aten._local_scalar_dense.default: SyncKind.SCALAR,
    _aten.nonzero.default: SyncKind.SHAPE,
    _aten.masked_select.default: SyncKind.SHAPE,
    _aten._unique.default: SyncKind.SHAPE,
    _aten._unique2.default: SyncKind.SHAPE,
    _aten.unique_dim.default: SyncKind.SHAPE,
    _aten.unique_consecutive.default: SyncKind.SHAPE,
    _aten.bincount.default: SyncKind.SHAPE,
    _aten.equal.default: SyncKind.SCALAR,
    _aten.is_nonzero.default: SyncKind.SCALAR,
    _aten._linalg_check_errors.default: SyncKind.ERROR_CHECK,
}


def _dispatch_level(func, args, kwargs) -> str | None:
    """The :class:`SyncKind` if the ATen call ``func(*args, **kwargs)`` synchronises."""
    kind = _DISPATCH_ALWAYS.get(func)
    if kind is not None:
        return kind
    packet = func.overloadpacket
    if packet is _aten.index and _has_bool_index(args[1]):
        return SyncKind.SHAPE
    if packet in (_aten.index_put, _aten.index_put_) and _has_bool_index(args[1]) and args[2].numel() != 1:
        return SyncKind.SHAPE
    if packet is _aten.repeat_interleave and func.__name__ != "repeat_interleave.self_int":
        if kwargs.get("output_size") is None:
            return SyncKind.SHAPE
    return None


def _display_name(func) -> str:
    """``Tensor.nonzero``, ``torch.where``: how the caller wrote a Python-level op."""
    name = getattr(func, "__name__", str(func))
    qual = getattr(func, "__qualname__", "")
    return f"Tensor.{name}" if qual.startswith(("TensorBase.", "Tensor.")) else f"torch.{name}"


class _FunctionLevel(TorchFunctionMode):
    def __init__(self, report: SyncReport):
        super().__init__()
        self.report = report
        self.stack: list[tuple[str, bool]] = []  # (Python-level op, recorded) being run
        self.host_copy = None  # result of the last call if it was a recorded copy to the host

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        hit = _python_level(func, args, kwargs)
        if hit is not None:
            # ``x.cpu().numpy()``: reading the host copy made just before is part of that copy
            if not (func in _READS_HOST and args and args[0] is self.host_copy):
                self.report.events.append(SyncEvent(hit[0], hit[1], _caller()))
        self.host_copy = None
        self.stack.append((_display_name(func), hit is not None))
        try:
            out = func(*args, **kwargs)
        finally:
            self.stack.pop()
        if hit is not None and hit[1] == SyncKind.COPY_TO_HOST:
            self.host_copy = out
        return out

    def recorded(self) -> bool:
        """Whether a Python-level op being run was recorded already."""
        return any(rec for _, rec in self.stack)


class _DispatchLevel(TorchDispatchMode):
    def __init__(self, report: SyncReport, python_level: _FunctionLevel):
        super().__init__()
        self.report = report
        self.python_level = python_level

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        kind = _dispatch_level(func, args, kwargs)
        if kind is not None and not self.python_level.recorded():
            op = f"aten.{func.__name__}"
            if self.python_level.stack:
                op += f" (in {self.python_level.stack[0][0]})"
            self.report.events.append(SyncEvent(op, kind, _caller()))
        return func(*args, **kwargs)


@contextlib.contextmanager
def count_syncs() -> Iterator[SyncReport]:
    """Record the operations in the ``with`` block that would synchronise on an accelerator.

    Works on every device (module docstring for what is recorded). Regions nest: an inner
    region's synchronisations are recorded in both reports.

    Yields:
        The :class:`SyncReport`, filled while the block runs.

    Example::

        with count_syncs() as syncs:
            y = x[x > 0].sum().item()
        syncs.count  # 2: the boolean mask and .item()
    """
    report = SyncReport()
    python_level = _FunctionLevel(report)
    with python_level, _DispatchLevel(report, python_level):
        yield report
