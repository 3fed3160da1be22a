"""A small bounded first-in-first-out cache for tables that are costly to rebuild per frame.

Keys are plain hashable tuples. They must be built from what is already on the host (shapes,
dtypes, devices, python numbers, frozen dataclasses) and never from tensor values: reading a
value of a tensor on an accelerator (``.item()``, ``.tolist()``, ``.cpu()``) waits for the
device, once per lookup. A table derived from a tensor is keyed on the tensor's identity
instead (``tensor_key``), and the entry keeps the tensor alive so that its ``id`` is not
reused while the entry exists.
"""

from __future__ import annotations

import threading
from typing import Callable, Generic, Hashable, TypeVar

from torch import Tensor

__all__ = ["FifoCache", "tensor_key"]

V = TypeVar("V")


class FifoCache(Generic[V]):
    """At most ``maxsize`` entries; when full, the oldest inserted entry is dropped.

    A hit does not refresh an entry's age (insertion order, not recency): the caches here
    hold a handful of cameras or sizes, where the two orders evict the same entries.

    Safe to share between threads (``run_sequence`` prepares frames on a thread of its own): an
    insertion and its eviction happen under a lock; two threads that miss the same key at once
    may both compute it, and the later value is kept.
    """

    def __init__(self, maxsize: int = 8):
        if not (isinstance(maxsize, int) and maxsize >= 1):
            raise ValueError(f"maxsize: expected a positive integer, got {maxsize!r}")
        self.maxsize = maxsize
        self._entries: dict[Hashable, V] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    def get(self, key: Hashable) -> V | None:
        """The value stored under ``key``, or None."""
        return self._entries.get(key)

    def put(self, key: Hashable, value: V) -> V:
        """Store ``value`` under ``key`` (dropping the oldest entry when full) and return it."""
        with self._lock:
            if key not in self._entries and len(self._entries) >= self.maxsize:
                self._entries.pop(next(iter(self._entries)))
            self._entries[key] = value
        return value

    def get_or_compute(self, key: Hashable, compute: Callable[[], V]) -> V:
        """The value under ``key``; on a miss, ``compute()`` is called once and its result stored."""
        hit = self._entries.get(key)
        if hit is not None:
            return hit
        return self.put(key, compute())

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


def tensor_key(t: Tensor) -> tuple:
    """A key naming ``t`` by identity and in-place version, with its shape, dtype and device.

    Reads no value, so it never waits for the device. An in-place change of ``t`` bumps its
    version and so misses; a different tensor with equal values misses too (the entry is only
    rebuilt). Store ``t`` in the cached value (or compare ``is``) so that its ``id`` cannot be
    reused by a new tensor while the entry lives.
    """
    return (id(t), t._version, tuple(t.shape), t.dtype, t.device)
