"""Frames read and prepared ahead in a forked child process (``AheadFrames`` in process mode).

On two cores a run's tracking thread shares the interpreter lock with the loader's decoding
thread and the thread that prepares frames ahead. Each of their NumPy, OpenCV and torch calls
releases the lock and takes it back, and every take-back while tracking holds it is a hand-over
that tracking waits for: a sparse tracking registration takes 1.3 x as long beside a thread
extracting ORB features and 1.5 x beside one decoding frames, and the same work in another
process costs it nothing measurable (``scripts/bench_contention.py``, docs/results/cpu.md, "What slows
tracking on two cores"). Here a child process forked after the system's ``start`` reads the
frames (decoding them) and runs the system's ``ahead_payload`` on each; the parent receives the
frame and its payload and hands them to ``accept_ahead``.

Tensors travel through a few shared-memory slots mapped before the fork, in turn: the child
writes the memory (storage) of a frame's tensors into the next free slot, each storage once
however many tensors view it (a frame's image and the batch view of it that the payload holds),
and sends a small pickle that refers to them; the parent copies each storage out into fresh
memory, rebuilds every tensor as the same view of it, and frees the slot. A storage that does
not fit its slot travels inside the pickle instead (slower, the same values). The parent gets
the very values the child computed, viewed as in the child, so a run gives the same results as
with the thread (tested).
"""

from __future__ import annotations

import io
import logging
import mmap
import multiprocessing
import pickle
import signal
import time
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import torch

from ..data.frame import Frame
from ..errors import TorchSlamError
from ..threads import name_os_thread

logger = logging.getLogger(__name__)

_ALIGN = 64
_SLOTS = 3


def available() -> bool:
    """Whether frames can be prepared in a child process here: the fork start method exists
    and this process may have children (a daemonic process, such as a ``multiprocessing.Pool``
    worker, may not: there the thread runs)."""
    return "fork" in multiprocessing.get_all_start_methods() and not multiprocessing.current_process().daemon


class _SlotPickler(pickle.Pickler):
    """Pickles CPU tensors by reference: each storage's bytes written once into ``buf``, each
    tensor as its view of them (dtype, shape, strides, offset)."""

    def __init__(self, file, buf: np.ndarray) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.buf = buf
        self.used = 0
        self.storages: dict[int, tuple[int, int, int]] = {}  # storage address -> (key, start, nbytes)
        self.keep: list[torch.Tensor] = []  # the tensors whose storages are in ``storages`` stay alive

    def persistent_id(self, obj: Any):
        if (type(obj) is not torch.Tensor or obj.device.type != "cpu" or obj.requires_grad
                or obj.layout != torch.strided or obj.numel() == 0):
            return None  # pickled by value (an empty tensor too: it has no bytes to share)
        t = obj.detach()
        if t.is_conj() or t.is_neg():
            t = t.resolve_conj().resolve_neg()  # the flags are not in the bytes
        storage = t.untyped_storage()
        known = self.storages.get(storage.data_ptr())
        if known is None:
            if storage.nbytes() > 2 * t.numel() * t.element_size() + _ALIGN or storage.nbytes() % t.element_size():
                # A storage much larger than its tensor (a row of a big batch) is not sent whole:
                # the tensor travels as a contiguous copy (so does one whose dtype does not tile
                # its storage).
                t = t.clone(memory_format=torch.contiguous_format)
                storage = t.untyped_storage()
            nbytes = storage.nbytes()
            start = -(-self.used // _ALIGN) * _ALIGN
            if start + nbytes > len(self.buf):
                return None  # pickled by value
            torch.from_numpy(self.buf[start : start + nbytes]).copy_(torch.empty(0, dtype=torch.uint8).set_(storage))
            known = self.storages[storage.data_ptr()] = (len(self.keep), start, nbytes)
            self.keep.append(t)
            self.used = start + nbytes
        key, start, nbytes = known
        dtype = str(t.dtype).removeprefix("torch.")
        return ("view", key, start, nbytes, dtype, tuple(t.shape), tuple(t.stride()), t.storage_offset())


class _SlotUnpickler(pickle.Unpickler):
    """Rebuilds the tensors ``_SlotPickler`` wrote into ``buf``: each storage copied into memory
    of its own, once, and each tensor the same view of it as in the writer."""

    def __init__(self, file, buf: np.ndarray) -> None:
        super().__init__(file)
        self.buf = buf
        self.made: dict[int, torch.Tensor] = {}  # key -> the storage's bytes, (nbytes,) uint8
        self.views: dict[tuple, torch.Tensor] = {}  # the same view twice: one tensor object

    def persistent_load(self, pid):
        kind, key, start, nbytes, dtype, shape, stride, offset = pid
        if kind != "view":
            raise pickle.UnpicklingError(f"unknown reference {kind!r}")
        t = self.views.get(pid)
        if t is None:
            raw = self.made.get(key)
            if raw is None:
                raw = self.made[key] = torch.from_numpy(self.buf[start : start + nbytes]).clone()
            t = self.views[pid] = raw.view(getattr(torch, dtype)).as_strided(shape, stride, offset)
        return t


def dumps(obj: Any, buf: np.ndarray) -> bytes:
    """``obj`` pickled, its CPU tensors' bytes written into ``buf`` (those that fit)."""
    out = io.BytesIO()
    _SlotPickler(out, buf).dump(obj)
    return out.getvalue()


def loads(data: bytes, buf: np.ndarray) -> Any:
    """What :func:`dumps` pickled, its tensors copied out of ``buf``."""
    return _SlotUnpickler(io.BytesIO(data), buf).load()


def _picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - an exception that cannot travel is named instead
        return TorchSlamError(f"{type(exc).__name__}: {exc}")


class ProcessSource:
    """The frames of ``source``, read and passed through ``system.ahead_payload`` in a child process.

    :meth:`next` returns ``(kind, value, seconds)`` as ``AheadFrames``' thread does: ``("frame",
    frame, s)`` after ``system.accept_ahead(frame, payload, stage_ms)`` (a frame whose payload
    failed is yielded unprepared: ``track`` prepares it inline and raises the error there),
    ``("error", exc, 0)`` for an error reading a frame, ``("end", None, 0)`` at the end. Frames
    the source skipped (``sequence.skipped``) are appended to the parent's ``sequence.skipped``.
    At most ``_SLOTS`` frames are ahead.
    """

    def __init__(self, system, source: Iterator[Frame], sequence=None, slot_bytes: int = 64 << 20) -> None:
        self.system = system
        self.sequence = sequence
        ctx = multiprocessing.get_context("fork")
        # Anonymous shared mappings, made before the fork: the child writes, the parent reads.
        self._maps = [mmap.mmap(-1, slot_bytes) for _ in range(_SLOTS)]
        self._bufs = [np.frombuffer(m, dtype=np.uint8) for m in self._maps]
        self._free = ctx.Semaphore(_SLOTS)
        self._stop = ctx.Event()
        recv, send = ctx.Pipe(duplex=False)
        self._conn = recv
        self.process = ctx.Process(target=_child, name="torchslam-ahead",
                                   args=(system, source, sequence, send, self._free, self._stop, self._bufs, cv2.getNumThreads()),
                                   daemon=True)
        self.process.start()
        send.close()
        self._done = False

    def next(self) -> tuple[str, Any, float]:
        if self._done:
            return "end", None, 0.0
        try:
            kind, slot, data, seconds, skipped = pickle.loads(self._conn.recv_bytes())
        except EOFError:
            self._done = True
            self.process.join(1.0)
            code = self.process.exitcode
            return "error", TorchSlamError(f"the process reading frames ahead ended unexpectedly (exit code {code})"), 0.0
        if skipped and self.sequence is not None and isinstance(getattr(self.sequence, "skipped", None), list):
            self.sequence.skipped.extend(skipped)
        if kind != "frame":
            self._done = True
            return kind, data, 0.0
        frame, payload, stage_ms, prepared = loads(data, self._bufs[slot])
        self._free.release()
        if prepared:
            self.system.accept_ahead(frame, payload, stage_ms)
        return "frame", frame, seconds

    def close(self) -> None:
        """Stop the child (frames it prepared and nobody took are dropped)."""
        self._stop.set()
        self._free.release()  # a child waiting for a slot sees the stop
        deadline = time.monotonic() + 10.0
        while self.process.is_alive() and time.monotonic() < deadline:
            # Drain what it still sends, so that it never blocks on a full pipe.
            while self._conn.poll(0.05):
                try:
                    self._conn.recv_bytes()
                except EOFError:
                    break
            self.process.join(0.01)
        if self.process.is_alive():
            logger.warning("the process reading frames ahead did not stop; terminating it")
            self.process.terminate()
            self.process.join()
        self._conn.close()
        self._done = True
        # The slots' memory goes now, not when this object is collected.
        self._bufs = []
        for m in self._maps:
            try:
                m.close()
            except BufferError:  # a view of it is still held somewhere: freed with that view
                pass


def _child(system, source, sequence, conn, free, stop, bufs, cv_threads: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent stops, then stops this process
    name_os_thread("tslam-ahead")
    # One intra-op thread whatever the parent's: OpenMP's thread pool does not survive a fork, and
    # a child that ran its parallel regions on the parent's count waited forever in libgomp for
    # workers that were never forked (``torchslam run --system gcslam --threads 2`` hung once the
    # parent had run a parallel region; tests/systems/test_ahead_process.py).
    torch.set_num_threads(1)
    # The parent's count again (a no-op for OpenCV): a different one here would rebuild OpenCV's
    # thread pool, whose threads did not survive the fork, and that hung in pthread_cond_destroy
    # (tried with 1 to spare ORB's second thread).
    cv2.setNumThreads(cv_threads)
    skipped_seen = len(getattr(sequence, "skipped", None) or ())
    slot = 0

    def new_skips() -> list:
        nonlocal skipped_seen
        skipped = getattr(sequence, "skipped", None)
        if not isinstance(skipped, list) or len(skipped) == skipped_seen:
            return []
        new, skipped_seen = skipped[skipped_seen:], len(skipped)
        return list(new)

    try:
        while True:
            while not free.acquire(timeout=0.05):
                if stop.is_set():
                    return
            if stop.is_set():
                return
            try:
                frame = next(source)
            except StopIteration:
                conn.send_bytes(pickle.dumps(("end", None, None, 0.0, new_skips())))
                return
            except BaseException as exc:  # noqa: BLE001 - raised by the parent in the frame's place
                conn.send_bytes(pickle.dumps(("error", None, _picklable(exc), 0.0, new_skips())))
                return
            t0 = time.perf_counter()
            try:
                payload, stage_ms = system.ahead_payload(frame)
                prepared = True
            except Exception:  # noqa: BLE001 - track prepares the frame inline and raises it there
                logger.debug("ahead_payload failed for frame %s; tracking prepares it", frame.index, exc_info=True)
                payload, stage_ms, prepared = None, {}, False
            data = dumps((frame, payload, stage_ms, prepared), bufs[slot])
            conn.send_bytes(pickle.dumps(("frame", slot, data, time.perf_counter() - t0, new_skips())))
            slot = (slot + 1) % len(bufs)
    except (BrokenPipeError, EOFError):  # the parent is gone or stopped reading
        return
    finally:
        close = getattr(source, "close", None)
        if close is not None:
            close()  # a generator's own prefetch thread stops with it
        conn.close()
