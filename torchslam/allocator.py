"""The C heap a run allocates its tensors from: freed memory kept for the next frame by default.

Every frame of NI-SLAM and GC-SLAM builds and frees the same few dozen tensors of 0.1-4 MB
(orthographic images, spectra, point clouds, pyramids). With glibc's default thresholds most of
them are handed back to the kernel when freed, either as their own ``mmap`` or by trimming the
top of the heap, so the next frame touches fresh pages again: about 1,300-2,400 minor page faults
per NI-SLAM tracking step on the 2-core benchmark machine, where a fault costs microseconds
under the hypervisor. Raising the thresholds keeps that memory in the process: the same step
then takes 5 faults, and runs about 1.2 x faster (docs/results/cpu.md, "The C heap kept between
frames").

``setup_allocator`` applies it to the whole process with ``mallopt`` (glibc only; elsewhere it
reports that nothing was changed). ``torchslam run``, ``torchslam batch``, ``calibrate-time`` and
the benchmarks call it; importing torchslam as a library changes nothing. The policy is
``retain``; ``TORCHSLAM_MALLOC=system`` leaves the C library's defaults alone. The price is
resident memory: what a frame freed stays mapped (up to ``TRIM_THRESHOLD`` above the heap's
top), so the resident size stays near its peak instead of falling back between frames.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform
from collections.abc import Mapping
from dataclasses import dataclass

from .errors import ConfigError

__all__ = ["ALLOCATOR_ENV", "AllocatorSetting", "MODES", "resolve_allocator", "setup_allocator"]

ALLOCATOR_ENV = "TORCHSLAM_MALLOC"
MODES = ("retain", "system")
POLICY_MODE = "retain"

# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

# Allocations above this still get their own mapping, returned on free (one-off big buffers).
MMAP_THRESHOLD = 32 << 20
# The heap's top is handed back only when this much lies free above the last used chunk.
TRIM_THRESHOLD = 256 << 20
# Each time the heap grows it grows by this much more, so a frame's burst does not grow it
# page by page.
TOP_PAD = 64 << 20


@dataclass(frozen=True)
class AllocatorSetting:
    """What ``setup_allocator`` chose and did.

    Attributes:
        mode: ``"retain"`` (freed memory kept for the next frame) or ``"system"`` (the C
            library's defaults).
        source: ``"env"`` (``TORCHSLAM_MALLOC``) or ``"policy"`` (the default).
        applied: the thresholds were set (``retain`` on glibc); False for ``system`` and where
            ``mallopt`` is not available.
        note: why nothing was applied, or ``""``.
    """

    mode: str
    source: str
    applied: bool
    note: str = ""

    def to_dict(self) -> dict[str, str | bool]:
        """The keys ``metrics.json`` records: ``malloc`` and ``malloc_applied``."""
        return {"malloc": self.mode, "malloc_applied": self.applied}


def resolve_allocator(environ: Mapping[str, str] | None = None) -> tuple[str, str]:
    """The mode and its source: ``TORCHSLAM_MALLOC`` if set, else the policy (``retain``).

    Raises:
        ConfigError: the variable is set to something other than ``retain`` or ``system``.
    """
    environ = os.environ if environ is None else environ
    raw = environ.get(ALLOCATOR_ENV)
    if raw is None or raw.strip() == "":
        return POLICY_MODE, "policy"
    mode = raw.strip().lower()
    if mode not in MODES:
        raise ConfigError(f"{ALLOCATOR_ENV}: expected one of {', '.join(MODES)}, got {raw!r}")
    return mode, "env"


def _mallopt():
    """glibc's ``mallopt``, or None (another C library, or none found)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallopt
    except (OSError, AttributeError):
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int)
    fn.restype = ctypes.c_int
    return fn


def setup_allocator(environ: Mapping[str, str] | None = None) -> AllocatorSetting:
    """Resolve the mode (:func:`resolve_allocator`) and apply it to this process.

    ``retain`` sets glibc's mmap threshold to 32 MiB, its trim threshold to 256 MiB and its top
    pad to 64 MiB. Calling it again is harmless. ``system`` changes nothing (thresholds an
    earlier call set stay set).
    """
    mode, source = resolve_allocator(environ)
    if mode == "system":
        return AllocatorSetting(mode, source, False, "the C library's defaults")
    mallopt = _mallopt()
    if mallopt is None:
        return AllocatorSetting(mode, source, False, "mallopt is glibc's; this C library's defaults stay")
    ok = all(
        mallopt(param, value) == 1
        for param, value in ((_M_MMAP_THRESHOLD, MMAP_THRESHOLD), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD), (_M_TOP_PAD, TOP_PAD))
    )
    return AllocatorSetting(mode, source, ok, "" if ok else "mallopt refused a threshold")
