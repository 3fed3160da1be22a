"""Stack per-system (1, ...) tensors into (B, ...) batches and split them back, without copies where possible.

The lockstep scheduler keeps each system's tensors as rows; a batched call stacks them
(``stack_rows``, ``stack_dataclass``), and its result is handed back as rows (``row``). Rows
that are consecutive rows of one tensor are stacked as a view of it, so state that stays the
same from one step to the next is not copied again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = ["dense", "groups", "row", "stack_dataclass", "stack_rows"]

D = TypeVar("D")


def groups(items: list[int], key: Callable[[int], Hashable]) -> list[list[int]]:
    """Split ``items`` (in order) by ``key``: the items that can share one batched call."""
    out: dict[Any, list[int]] = {}
    for i in items:
        out.setdefault(key(i), []).append(i)
    return list(out.values())


def dense(t: Tensor) -> bool:
    """Whether ``t`` covers one gap-free block of its storage in some dimension order.

    True for contiguous tensors and for permuted views of them, such as the (1, N, 3) rows of
    ``rgbd_to_points``' clouds, which are stored as (1, 3, N) coordinate planes.
    """
    expected = 1
    for stride, size in sorted((st, sz) for st, sz in zip(t.stride(), t.shape) if sz > 1):
        if stride != expected:
            return False
        expected *= size
    return True


def stack_rows(rows: list[Tensor]) -> Tensor:
    """Concatenate (1, ...) tensors along dim 0, without a copy where they are consecutive rows of one tensor.

    Rows of one batch keep their memory layout (e.g. the coordinate planes of a point cloud) in
    the stacked view; a copy (``torch.cat``) is made only where they are not consecutive.

    Args:
        rows: B tensors of shape (1, ...), equal shapes.

    Returns:
        (B, ...) tensor.
    """
    first = rows[0]
    if len(rows) == 1:
        return first
    step = first.numel()
    storage = first.untyped_storage().data_ptr()
    if dense(first) and all(
        r.shape == first.shape and r.stride() == first.stride() and r.dtype == first.dtype and r.device == first.device
        and r.untyped_storage().data_ptr() == storage and r.storage_offset() == first.storage_offset() + k * step
        for k, r in enumerate(rows)
    ):
        return first.as_strided((len(rows), *first.shape[1:]), (step, *first.stride()[1:]))
    return torch.cat(rows)


def stack_dataclass(items: list[D]) -> D:
    """Stack frozen dataclasses of (1, ...) tensors (KeyframeMap, KCCFilter, OrthoImages) along B.

    Tensor fields go through ``stack_rows``, nested dataclasses recursively; other fields (sizes)
    are taken from the first item.
    """
    if len(items) == 1:
        return items[0]
    values = {}
    for f in dataclasses.fields(items[0]):
        v = getattr(items[0], f.name)
        if isinstance(v, Tensor):
            values[f.name] = stack_rows([getattr(x, f.name) for x in items])
        elif dataclasses.is_dataclass(v):
            values[f.name] = stack_dataclass([getattr(x, f.name) for x in items])
        else:
            values[f.name] = v
    return type(items[0])(**values)


def row(batch: D, k: int) -> D:
    """Row ``k`` of a dataclass of (B, ...) tensors, as (1, ...) views."""
    values = {}
    for f in dataclasses.fields(batch):
        v = getattr(batch, f.name)
        if isinstance(v, Tensor):
            values[f.name] = v[k : k + 1]
        elif dataclasses.is_dataclass(v):
            values[f.name] = row(v, k)
        else:
            values[f.name] = v
    return type(batch)(**values)
