"""Reading torchslam checkpoints: ``torch.save`` files of plain data, read without running code.

The format (written by ``torchslam.learn.save_checkpoint``)::

    {"format": "torchslam-params", "version": 1, "kind": "config" | "module",
     "config_type": "NISlamConfig" | None, "values": {"kcc.sigma": 0.23, ...},
     "module": "KCCFeatureNet", "state_dict": {...}, "extra": {...}}

Reading sits low in the package so that a module that ships trained weights (the learned KCC
feature channels, ``torchslam.kcc.features``) can load them without importing ``learn/``.
"""

from __future__ import annotations

import math
import os
import pickle
import re
from pathlib import Path
from typing import Any

import torch

from .errors import DataFormatError

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "load_checkpoint"]

CHECKPOINT_FORMAT = "torchslam-params"
CHECKPOINT_VERSION = 1


def _load_failure(exc: Exception) -> str:
    """One line saying why ``torch.load(weights_only=True)`` refused a file.

    PyTorch's own message for a refused pickle spans several lines of advice (ending in how to
    load the file with ``weights_only=False``, which would run its code); only the reason is kept.
    """
    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) and "Weights only load failed" in text:
        found = re.search(r"GLOBAL (\S+) was not an allowed global", text)
        if found:
            return (
                f"refused as an unsafe pickle that would import {found.group(1)}; torchslam reads "
                "checkpoints as plain data only, so that loading one never runs code"
            )
        reason = text.split("WeightsUnpickler error:", 1)[1] if "WeightsUnpickler error:" in text else ""
        reason = " ".join(reason.split("Check the documentation")[0].split())
        return f"not plain pickled data: {reason}" if reason else "not plain pickled data"
    if isinstance(exc, EOFError):
        return "the file ends early"
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    first = first.split(". ")[0][:200]
    return f"{exc.__class__.__name__}: {first}" if first else exc.__class__.__name__


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs).

    Returns:
        The stored dict (``format``, ``kind``, ``config_type``, ``values``, ``state_dict``, ``extra``...).

    Raises:
        DataFormatError: naming the file when it is missing, unreadable or not such a checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: no such checkpoint file")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle, zip and weights-only errors all mean "not a checkpoint"
        raise DataFormatError(f"{path}: not a readable torchslam checkpoint ({_load_failure(exc)})") from exc
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise DataFormatError(f"{path}: not a torchslam parameter checkpoint (no format: {CHECKPOINT_FORMAT!r})")
    if doc.get("version") != CHECKPOINT_VERSION:
        raise DataFormatError(f"{path}: checkpoint version {doc.get('version')!r}; this torchslam reads version {CHECKPOINT_VERSION}")
    for key, kind in (("values", dict), ("state_dict", dict), ("extra", dict), ("kind", str)):
        if not isinstance(doc.get(key), kind):
            raise DataFormatError(f"{path}: checkpoint field {key!r} is missing or not a {kind.__name__}")
    for key, v in doc["values"].items():
        if not isinstance(key, str) or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DataFormatError(f"{path}: value {key!r} = {v!r} is not a finite number")
    return doc
