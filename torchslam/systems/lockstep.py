"""Many sequences in lockstep: one frame of every sequence per step, through the one driver.

``run_lockstep`` is to a group of sequences what ``run_sequence`` is to one, and both are the
same loop (``base.drive``: Ctrl-C, timing, finish, skipped frames, memory check): it builds one
system per sequence from the config's registered ``SystemSpec`` and steps them with the system's
batched step (``SystemSpec.lockstep``). NI-SLAM batches its per-frame tensor work
(back-projection and tracking step) across sequences and runs fusion, keyframes and loop
closure per sequence (``nislam.track_frames``); GC-SLAM tracks each frame on its own and
optimises the new keyframes of all sequences in one FastGO call (``gcslam.track_frames``). A
system without a lockstep step is advanced one ``track`` after the other. Each returned
``RunResult`` equals what ``run_sequence`` gives for that sequence alone, up to floating-point
round-off of the batched kernels. The timing conventions are ``base.drive``'s.
"""

from __future__ import annotations

import logging

from ..data.frame import Sequence
from ..errors import ConfigError
from .base import RunResult, drive, track_each
from .monitor import Monitor
from .registry import SystemSpec, spec_for_config

__all__ = ["default_max_batch", "run_lockstep"]

logger = logging.getLogger(__name__)


def _spec(system_cfg) -> SystemSpec:
    try:
        return spec_for_config(system_cfg)
    except ConfigError:
        raise ConfigError(
            f"system_cfg: expected the config of an available system, got {type(system_cfg).__name__}"
        ) from None


def default_max_batch(system_cfg, device: str, n: int) -> int:
    """Sequences per batched call when none is given: the system's choice (``LockstepSpec.max_batch``), else all ``n``."""
    lockstep = _spec(system_cfg).lockstep
    if lockstep is None or lockstep.max_batch is None:
        return max(n, 1)
    return lockstep.max_batch(system_cfg, device, n)


def run_lockstep(
    system_cfg,
    sequences: list[Sequence],
    device: str = "cpu",
    monitors: list[Monitor] | None = None,
    max_frames: int | None = None,
    max_batch: int | None = None,
) -> list[RunResult | BaseException]:
    """Run a registered system on several sequences at once, one frame of each per step.

    Args:
        system_cfg: the system's settings (NI-SLAM's or GC-SLAM's config), shared by every sequence.
        sequences: the sequences; any lengths, cameras and image sizes.
        device: where tensors live ("cpu", "cuda", ...).
        monitors: one monitor per sequence, or None for no monitoring.
        max_frames: stop each sequence after this many frames.
        max_batch: the most sequences in one batched call; None takes ``default_max_batch``.

    Returns:
        Per sequence, in order, its ``RunResult`` or the exception that stopped it.

    Raises:
        ConfigError: an argument is not what it should be (named in the message), or the
            configuration needs more memory than the device has (``systems.memory``).
    """
    spec = _spec(system_cfg)
    if not isinstance(sequences, (list, tuple)) or not sequences:
        raise ConfigError(f"sequences: expected a non-empty list of sequences, got {sequences!r}")
    if monitors is not None and len(monitors) != len(sequences):
        raise ConfigError(f"monitors: expected one monitor per sequence ({len(sequences)}), got {len(monitors)}")
    if max_frames is not None and not (isinstance(max_frames, int) and max_frames >= 0):
        raise ConfigError(f"max_frames: expected a non-negative integer or None, got {max_frames!r}")
    if max_batch is not None and not (isinstance(max_batch, int) and max_batch >= 1):
        raise ConfigError(f"max_batch: expected a positive integer or None, got {max_batch!r}")
    n = len(sequences)
    if max_batch is None:
        max_batch = default_max_batch(system_cfg, device, n)
    monitors = list(monitors) if monitors is not None else [Monitor() for _ in range(n)]
    lockstep = spec.lockstep
    build = lockstep.build if lockstep is not None and lockstep.build is not None else spec.build
    systems = [build(system_cfg, device=device, monitor=m) for m in monitors]
    step = lockstep.step if lockstep is not None else track_each
    holds_all = lockstep is not None and lockstep.holds_all
    return drive(systems, list(sequences), step, max_batch=max_batch, max_frames=max_frames,
                 memory_batch=n if holds_all else 1)
