"""Memory a configuration needs, estimated before anything runs, and the refusal when it cannot fit.

The estimate is the peak resident memory per pixel measured on the CPU (float32 images,
``resource.getrusage`` maximum RSS of NI-SLAM and GC-SLAM runs on synthetic sequences at several
sizes, one thread), times the pixel counts a configuration implies:

- NI-SLAM: ``NISLAM_BYTES_PER_ORTHO_PIXEL`` per orthographic pixel (``kcc.ortho_height x
  kcc.ortho_width``) and sequence in the batch: projected grey, depth and mask, the two KCC
  channels, their rfft2 spectra, the keyframe map and filter, the correlation output and the
  sub-pixel and fusion temporaries (from runs at 2048^2 and 3072^2);
- both systems: ``BYTES_PER_IMAGE_PIXEL`` per input image pixel and sequence (decoded colour and
  depth, back-projected points and rays, ORB; from runs at 640 x 480 and 1280 x 960);
- GC-SLAM with the dense front-end: ``DENSE_BYTES_PER_WORKING_PIXEL`` per pixel of the dense
  working resolution (the image reduced by ``round(W / dense.width)``): the pyramid of both frames,
  the Jacobian rows and IRLS weights (from runs at 1280 x 960);
- GC-SLAM with ``keyframe_pairs`` dense (the sparse front-end's default): ``DENSE_PAIR_BYTES_PER_WORKING_PIXEL``
  per pixel of that working resolution in the optimiser: the pyramids of the last keyframes used
  and a batch of loop registrations (the peak-RSS difference of a 7-Scenes run with and without,
  160 MB at 320 x 240, rounded up), plus the keyframes' working images, which grow with the run
  (about 8 bytes a working pixel a keyframe, not counted).

A configuration whose estimate exceeds the device's total memory (physical RAM on the CPU, the
GPU's memory on CUDA) is refused with the figure instead of dying in an allocation part-way.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from ..errors import ConfigError
from ..geometry import PinholeCamera
from .registry import spec_for_config

__all__ = [
    "BYTES_PER_IMAGE_PIXEL", "DENSE_BYTES_PER_WORKING_PIXEL", "DENSE_PAIR_BYTES_PER_WORKING_PIXEL", "InsufficientMemoryError", "MemoryEstimate",
    "NISLAM_BYTES_PER_ORTHO_PIXEL", "check_memory", "check_run_memory", "device_memory", "estimate_memory",
]

# The largest per-pixel peak of each part over those runs, rounded up: an upper bound, not a mean.
NISLAM_BYTES_PER_ORTHO_PIXEL = 368
BYTES_PER_IMAGE_PIXEL = 336
DENSE_BYTES_PER_WORKING_PIXEL = 528
DENSE_PAIR_BYTES_PER_WORKING_PIXEL = 2400


class InsufficientMemoryError(ConfigError):
    """A configuration needs more memory than the device has; the message gives both figures."""


@dataclass(frozen=True)
class MemoryEstimate:
    """Estimated peak memory of a configuration.

    Attributes:
        total: bytes.
        parts: bytes per part (``"orthographic images"``, ``"input images"``, ``"dense pyramid"``).
        hint: the settings that drive the largest part, for the message.
    """

    total: int
    parts: dict[str, int]
    hint: str


def estimate_memory(cfg, camera: PinholeCamera, batch: int = 1) -> MemoryEstimate:
    """Estimate the peak memory of running ``cfg`` (any registered system's config) on ``batch``
    sequences of ``camera``'s image size (module docstring for the figures).

    The input images are common to every system; the system's own parts come from its
    ``SystemSpec.memory`` as ``{part: (bytes, the settings behind it)}``.

    Raises:
        ConfigError: for a config that belongs to no registered system.
    """
    spec = spec_for_config(cfg)
    image_px = camera.width * camera.height
    parts = {"input images": (BYTES_PER_IMAGE_PIXEL * image_px * batch, f"image {camera.width}x{camera.height}")}
    if spec.memory is not None:
        parts.update(spec.memory(cfg, camera, batch))
    hint = max(parts.values(), key=lambda part: part[0])[1]
    if batch > 1:
        hint += f", {batch} sequences per batch"
    return MemoryEstimate(sum(b for b, _ in parts.values()), {name: b for name, (b, _) in parts.items()}, hint)


def device_memory(device: str | torch.device) -> int | None:
    """Total memory of ``device`` in bytes (physical RAM for the CPU), or None when unknown."""
    dev = torch.device(device)
    if dev.type == "cuda":
        try:
            return int(torch.cuda.get_device_properties(dev).total_memory)
        except (RuntimeError, AssertionError, ValueError):  # no such GPU: the run itself says so
            return None
    if dev.type == "cpu":
        try:
            return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            return None
    return None


def _gb(n: int) -> str:
    return f"{n / 1e9:.3g} GB" if n < 1e11 else f"{n / 1e9:,.0f} GB"


def check_memory(
    cfg, camera: PinholeCamera, device: str | torch.device = "cpu", batch: int = 1, available: int | None = None
) -> MemoryEstimate:
    """Refuse a configuration whose estimated memory exceeds the device's, before anything is allocated.

    Args:
        cfg: a registered system's config.
        camera: the sequence's camera (its image size).
        device: where the run's tensors live.
        batch: sequences processed together.
        available: bytes to compare against; None takes ``device_memory(device)`` (no check when
            that is unknown).

    Returns:
        The estimate.

    Raises:
        InsufficientMemoryError: naming the estimate, its largest part and the settings behind it, and the
            device's memory.
    """
    est = estimate_memory(cfg, camera, batch)
    limit = device_memory(device) if available is None else available
    if limit is not None and est.total > limit:
        parts = ", ".join(f"{name} ~{_gb(b)}" for name, b in sorted(est.parts.items(), key=lambda kv: -kv[1]))
        raise InsufficientMemoryError(
            f"this configuration needs ~{_gb(est.total)} of memory ({parts}; {est.hint}), "
            f"but {torch.device(device)} has {_gb(limit)}"
        )
    return est


def check_run_memory(system, cameras: list[PinholeCamera], batch: int = 1) -> MemoryEstimate | None:
    """``check_memory`` for a built ``system`` (its ``cfg`` and ``device``) on the largest of
    ``cameras``; None (no check) for a system whose config no registered system owns, or no camera."""

    cfg = getattr(system, "cfg", None)
    cameras = [c for c in cameras if isinstance(c, PinholeCamera)]
    if cfg is None or not cameras:
        return None
    try:
        spec_for_config(cfg)
    except ConfigError:
        return None
    camera = max(cameras, key=lambda c: c.width * c.height)
    return check_memory(cfg, camera, getattr(system, "device", "cpu"), batch)
