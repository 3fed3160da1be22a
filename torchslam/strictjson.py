"""Strict JSON text: what torchslam writes and prints holds no ``Infinity`` or ``NaN`` tokens.

Python's ``json`` writes non-finite floats as ``Infinity``/``NaN``, which strict JSON readers
(browsers, ``jq``, most languages) reject. :func:`dumps` replaces every non-finite number with
``null`` and, where the document is a mapping, records why under ``"non_finite"``: the path of
each replaced value and what it was (``"inf"``, ``"-inf"`` or ``"nan"``). The text is then
written with ``allow_nan=False``, so a stray non-finite value cannot slip through.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["NON_FINITE_KEY", "dumps", "finite_or_none", "sanitize"]

NON_FINITE_KEY = "non_finite"


def finite_or_none(value: Any) -> float | None:
    """``float(value)`` when it is a finite number, else None."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _plain(value: Any) -> Any:
    """Tensors, NumPy scalars/arrays and paths as plain Python values (others unchanged)."""
    if isinstance(value, Path):
        return str(value)
    tolist = getattr(value, "tolist", None)
    if callable(tolist) and type(value).__module__.split(".")[0] in ("torch", "numpy"):
        return tolist()
    return value


def sanitize(obj: Any, path: str = "") -> tuple[Any, dict[str, str]]:
    """Return ``obj`` with every non-finite float replaced by None, and what was replaced.

    Args:
        obj: JSON-like data (dicts, lists, tuples, numbers, strings, bools, None; tensors,
            NumPy values and paths are converted).
        path: the location of ``obj`` in its document (dotted keys, ``[i]`` for list items).

    Returns:
        (clean copy, ``{path: "inf" | "-inf" | "nan"}`` of the replaced values).
    """
    replaced: dict[str, str] = {}

    def walk(v: Any, where: str) -> Any:
        v = _plain(v)
        if isinstance(v, bool) or v is None or isinstance(v, (str, int)):
            return v
        if isinstance(v, float):
            if math.isfinite(v):
                return v
            replaced[where or "."] = "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
            return None
        if isinstance(v, Mapping):
            return {str(k): walk(x, f"{where}.{k}" if where else str(k)) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]
        raise TypeError(f"not JSON serialisable: {type(v).__name__} at {where or '.'}")

    return walk(obj, path), replaced


def dumps(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj``: non-finite numbers become null, listed under ``"non_finite"``.

    A mapping's existing ``"non_finite"`` entries are kept and extended. Non-mapping documents
    get the nulls without the list (there is nowhere to put it).
    """
    clean, replaced = sanitize(obj)
    if replaced and isinstance(clean, dict):
        notes = clean.get(NON_FINITE_KEY)
        notes = dict(notes) if isinstance(notes, dict) else {}
        notes.update(replaced)
        clean[NON_FINITE_KEY] = notes
    return json.dumps(clean, indent=indent, allow_nan=False)
