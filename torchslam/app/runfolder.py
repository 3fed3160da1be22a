"""The run folder on disk: checked before a run starts, cleared only when it holds a run, locked for a batch.

A run folder holds only files torchslam writes (:data:`RUN_FILES` and TensorBoard event files).
``torchslam run`` checks its ``--out`` before any data is read, so a folder it cannot write
into, or one that holds an earlier run, is refused at once instead of after tracking the whole
sequence. ``torchslam batch`` takes a lock on its folder so two batches never mix their files.
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path

from ..errors import TorchSlamError

__all__ = [
    "BATCH_LOCK_FILE",
    "RUN_FILES",
    "BatchLock",
    "OutputFolderError",
    "OutputWriteError",
    "check_writable",
    "is_run_file",
    "prepare_run_folder",
]

logger = logging.getLogger(__name__)

# Every file a run folder can hold besides TensorBoard's event files (batch adds the last two).
RUN_FILES = ("trajectory.txt", "keyframes.txt", "map.ply", "metrics.json", "config.yaml", "groundtruth.txt", "error.txt")
EVENTS_PREFIX = "events.out.tfevents."
BATCH_LOCK_FILE = ".torchslam-batch.lock"
_PROBE_PREFIX = ".torchslam-write-test-"


class OutputFolderError(TorchSlamError, ValueError):
    """An output folder cannot take a run (not a folder, not writable, not empty); names the folder."""


class OutputWriteError(TorchSlamError, OSError):
    """Writing a run's outputs failed for some files; the others were written.

    Attributes:
        folder: the run folder.
        written: names of the files that were written.
        failed: (name, reason) of the files that were not.
    """

    def __init__(self, folder: Path, written: list[str], failed: list[tuple[str, str]]) -> None:
        self.folder, self.written, self.failed = Path(folder), list(written), list(failed)
        what = "; ".join(f"{self.folder / name}: {why}" for name, why in failed)
        kept = ", ".join(written) if written else "nothing"
        super().__init__(f"cannot write {what} (kept in {self.folder}: {kept})")


def is_run_file(name: str) -> bool:
    """Whether a file called ``name`` is one torchslam writes into a run folder."""
    return name in RUN_FILES or name.startswith(EVENTS_PREFIX) or name.startswith(_PROBE_PREFIX)


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def check_writable(folder: Path, what: str) -> None:
    """Create and remove a file in ``folder``: permission bits, a read-only mount and an immutable
    folder all show up here (``os.access`` misses the last two and everything for root)."""
    probe = folder / f"{_PROBE_PREFIX}{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise OutputFolderError(f"{what}: cannot write into {folder} ({_reason(exc)})") from exc
    os.close(fd)
    try:
        os.unlink(probe)
    except OSError as exc:
        raise OutputFolderError(f"{what}: cannot remove files in {folder} ({_reason(exc)})") from exc


def prepare_run_folder(out: str | os.PathLike, overwrite: bool = False, what: str = "--out") -> None:
    """Make sure ``out`` can take a new run before anything is computed.

    A missing folder is not created here (a run that fails before its first frame leaves none);
    its nearest existing parent must be a writable folder. An existing folder must be writable
    and empty. With ``overwrite`` a non-empty folder is cleared, but only when every entry in it
    is a file torchslam writes into a run folder: a folder holding anything else (a batch
    folder, a home folder, sub-folders) is refused rather than cleared.

    Raises:
        OutputFolderError: naming the folder and why it cannot be used.
    """
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise OutputFolderError(f"{what} {out}: exists and is not a folder")
        try:
            entries = sorted(os.listdir(out))
        except OSError as exc:
            raise OutputFolderError(f"{what} {out}: cannot list the folder ({_reason(exc)})") from exc
        if entries and not overwrite:
            raise OutputFolderError(
                f"{what} {out}: the folder is not empty ({len(entries)} entries, e.g. {entries[0]}), so it would mix "
                f"two runs; choose another folder or pass --overwrite to clear it"
            )
        foreign = [e for e in entries if not (is_run_file(e) and (out / e).is_file() and not (out / e).is_symlink())]
        if foreign:
            more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
            raise OutputFolderError(
                f"{what} {out}: --overwrite refused: {foreign[0]!r}{more} is not a file torchslam writes into a run "
                f"folder; clear or choose the folder yourself"
            )
        check_writable(out, f"{what} {out}")
        for e in entries:
            try:
                (out / e).unlink()
            except OSError as exc:
                raise OutputFolderError(f"{what} {out}: cannot clear {e} ({_reason(exc)})") from exc
        if entries:
            logger.warning("%s: cleared %d files of an earlier run (--overwrite)", out, len(entries))
        return
    parent = out.absolute().parent
    while not (parent.exists() or parent.is_symlink()):
        parent = parent.parent
    if not parent.is_dir():
        raise OutputFolderError(f"{what} {out}: cannot create the folder: {parent} is a file, not a folder")
    check_writable(parent, f"{what} {out}")


class BatchLock:
    """An exclusive ``flock`` on ``<folder>/.torchslam-batch.lock`` holding the owner's pid.

    The lock dies with its process, so a crashed batch never leaves a stale lock behind; the
    file itself stays (removing it would race with a batch that just opened it).
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.path = Path(folder) / BATCH_LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock or raise OutputFolderError naming the process that holds it."""
        try:
            import fcntl
        except ImportError:  # no flock on this platform: run unlocked
            logger.warning("%s: no file locking on this platform; do not run two batches on one folder", self.path)
            return
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputFolderError(f"--out {self.path.parent}: cannot create {self.path.name} ({_reason(exc)})") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise OutputFolderError(f"--out {self.path.parent}: cannot lock {self.path} ({_reason(exc)})") from exc
            raise OutputFolderError(
                f"--out {self.path.parent}: another torchslam batch (pid {holder}) is writing into this folder "
                f"(lock {self.path}); wait for it to finish or choose another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._fd = fd

    def release(self) -> None:
        """Give the lock up (closing the file releases the flock)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
