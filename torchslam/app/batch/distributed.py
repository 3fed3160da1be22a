"""Running a batch under ``torchrun``: joining the process group, the ranks' share of the
sequences, the batch folder's lock taken once for the group, and gathering the rows.

Under ``torchrun`` (``RANK``, ``WORLD_SIZE`` and ``MASTER_ADDR`` in the environment) the process
group is initialised (gloo on the CPU, NCCL with ``device="cuda"``), sequence ``i`` goes to rank
``i % world_size`` (:func:`shard`), each rank writes its own run folders, and the rows are
gathered with ``all_gather_object`` so that rank 0 writes the one summary.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

from ...errors import ConfigError
from ..runfolder import BatchLock, OutputFolderError
from .sources import BatchSource
from .summary import summary_row

__all__ = ["DIST_TIMEOUT", "Dist", "gather_rows", "init_distributed", "lock_batch_folder", "shard", "sigterm_as_interrupt"]

logger = logging.getLogger(__name__)

# Ranks wait for the slowest one at the final gather; a batch can take hours.
DIST_TIMEOUT = timedelta(hours=12)


@dataclass(frozen=True)
class Dist:
    """This process's place in the process group.

    Attributes:
        rank, world_size: as torchrun numbers them (0 and 1 when running alone).
        local_rank: the rank on this machine (its GPU under NCCL).
        initialised_here: this batch initialised the process group (and destroys it at the end).
        active: a process group exists.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    initialised_here: bool = False
    active: bool = False


def _env_int(key: str) -> int:
    try:
        return int(os.environ[key])
    except ValueError as exc:
        raise ConfigError(f"environment {key}={os.environ[key]!r}: expected an integer") from exc


def init_distributed(device: str) -> Dist:
    """Join the torchrun process group where the environment names one; else run alone."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return Dist(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")), False, True)
    if "RANK" not in os.environ or "WORLD_SIZE" not in os.environ:
        return Dist()
    for key in ("MASTER_ADDR", "MASTER_PORT"):
        if key not in os.environ:
            raise ConfigError(f"environment: RANK and WORLD_SIZE are set but {key} is not (start the batch with torchrun)")
    if not dist.is_available():
        raise ConfigError("environment: RANK/WORLD_SIZE are set but this PyTorch build has no torch.distributed")
    rank, world = _env_int("RANK"), _env_int("WORLD_SIZE")
    local = _env_int("LOCAL_RANK") if "LOCAL_RANK" in os.environ else 0
    backend = "gloo"
    if device == "cuda":
        import torch

        torch.cuda.set_device(local)
        backend = "nccl"
    dist.init_process_group(backend=backend, init_method="env://", rank=rank, world_size=world, timeout=DIST_TIMEOUT)
    logger.info("rank %d of %d (%s)", rank, world, backend)
    return Dist(rank, world, local, True, True)


@contextmanager
def sigterm_as_interrupt(enabled: bool) -> Iterator[None]:
    """Under torchrun a Ctrl-C reaches the workers as SIGINT and then SIGTERM from the agent:
    treat the first SIGTERM like Ctrl-C so the run finishes cleanly, ignore later ones."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    fired = False

    def handler(signum, frame):
        nonlocal fired
        if not fired:
            fired = True
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def lock_batch_folder(out: Path, dist: Dist) -> BatchLock | None:
    """Take the batch folder's lock on rank 0; every rank raises if it is held by another batch."""
    lock, message = None, None
    if dist.rank == 0:
        try:
            out.mkdir(parents=True, exist_ok=True)
            lock = BatchLock(out)
            lock.acquire()
        except OSError as exc:
            message = f"--out {out}: cannot create the folder ({exc.strerror or exc})"
        except OutputFolderError as exc:
            message = str(exc)
    if dist.world_size > 1:
        import torch.distributed as tdist

        box = [message]
        tdist.broadcast_object_list(box, src=0)
        message = box[0]
    if message is not None:
        if lock is not None:
            lock.release()
        raise OutputFolderError(message)
    return lock


def shard(sources: list[BatchSource], dist: Dist) -> list[BatchSource]:
    """The sequences this rank runs: ``i % world_size == rank``."""
    return sources[dist.rank :: dist.world_size]


def gather_rows(
    dist: Dist,
    sources: list[BatchSource],
    rows: dict[int, dict[str, Any]],
    wall: float,
    interrupted: bool,
    completed: Callable[[BatchSource], dict[str, Any] | None],
) -> tuple[dict[int, dict[str, Any]], list[float], bool]:
    """Bring every rank's rows to every rank; after an interruption rank 0 reads the others' folders.

    Args:
        dist: this process's place in the group.
        sources: all the batch's sequences.
        rows: this rank's rows by sequence index.
        wall: this rank's wall time, seconds.
        interrupted: this rank was interrupted.
        completed: the metrics of a sequence's complete run on disk, or None (``completed_run``).

    Returns:
        (rows of all ranks by sequence index, each rank's wall time, whether any rank was interrupted).
    """
    if dist.world_size == 1:
        return rows, [wall], interrupted
    if not interrupted:
        import torch.distributed as tdist

        gathered: list[Any] = [None] * dist.world_size
        try:
            tdist.all_gather_object(gathered, (rows, wall, interrupted))
        except KeyboardInterrupt:  # Ctrl-C while waiting for a slower rank
            gathered = None
        if gathered is not None:
            merged: dict[int, dict[str, Any]] = {}
            for r, _, _ in gathered:
                merged.update(r)
            return merged, [w for _, w, _ in gathered], any(i for _, _, i in gathered)
    # Another rank may already be gone, so no collective: what the others finished is on disk.
    merged = dict(rows)
    for src in sources:
        if src.index in merged:
            continue
        done = completed(src)
        merged[src.index] = (
            summary_row(src, "ok", done, "read from its folder after the interruption")
            if done is not None
            else summary_row(src, "not run", message="another rank's sequence; not finished at the interruption")
        )
    return merged, [wall], True


