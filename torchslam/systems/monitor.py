"""Experiment monitors: the no-op default and a TensorBoard writer.

Systems never open TensorBoard themselves; a ``Monitor`` is injected by whoever runs them, so the
library stays free of disk I/O and a run without monitoring costs nothing.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

__all__ = ["Monitor", "TensorBoardMonitor"]

logger = logging.getLogger(__name__)


class Monitor:
    """No-op monitor; subclasses write scalars, images and hyper-parameters somewhere."""

    def scalar(self, tag: str, value: float, step: int) -> None:
        """Record one scalar."""

    def scalars(self, values: Mapping[str, float], step: int, prefix: str = "") -> None:
        """Record several scalars under ``prefix``."""
        for k, v in values.items():
            self.scalar(f"{prefix}{k}", v, step)

    def image(self, tag: str, image: Tensor, step: int) -> None:
        """Record a ``(C, H, W)`` image with values in [0, 1] (C = 1 or 3)."""

    def hparams(self, hparams: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
        """Record the run's hyper-parameters beside its final metrics."""

    def close(self) -> None:
        """Flush and release resources."""


class TensorBoardMonitor(Monitor):
    """Write TensorBoard event files into ``logdir``.

    The event file (and the folder) is created at the first record, so a run that fails before
    producing anything leaves no half-made run folder behind.
    """

    def __init__(self, logdir: str | os.PathLike) -> None:
        self.logdir = str(logdir)
        self._w = None

    @property
    def _writer(self):
        if self._w is None:
            try:
                from torch.utils.tensorboard import SummaryWriter  # imported lazily: heavy
            except ImportError as exc:
                # TensorBoard is optional at run time: without it the monitor records nothing,
                # says so once, and the run's own results are unaffected.
                logger.warning("TensorBoard events not written: %s (install tensorboard to get them)", exc)
                self._w = _NullWriter()
                return self._w
            self._w = SummaryWriter(self.logdir)
        return self._w

    def scalar(self, tag: str, value: float, step: int) -> None:
        self._writer.add_scalar(tag, float(value), step)

    def image(self, tag: str, image: Tensor, step: int) -> None:
        img = image.detach().float().clamp(0, 1).cpu()
        if img.dim() == 2:
            img = img[None]
        self._writer.add_image(tag, img, step, dataformats="CHW")

    def hparams(self, hparams: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
        flat = {k: v if isinstance(v, (int, float, str, bool, torch.Tensor)) else str(v) for k, v in _flatten(hparams).items()}
        clean = {f"hparam/{k}": float(v) for k, v in metrics.items() if isinstance(v, (int, float)) and v == v}
        self._writer.add_hparams(flat, clean, run_name=".")

    def close(self) -> None:
        if self._w is not None:
            self._w.flush()
            self._w.close()


class _NullWriter:
    """Stands in for ``SummaryWriter`` when TensorBoard is not installed: every call does nothing."""

    def __getattr__(self, name: str):
        return lambda *args, **kwargs: None


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        elif v is not None:
            out[key] = v
    return out
