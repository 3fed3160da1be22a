"""GC-SLAM's optimisation side: keyframe poses, pairs, MILD loop detection and FastGO.

The tracker hands each new keyframe over as a :class:`KeyframeEvent`. An :class:`Optimizer`
holds what the optimisation thread owns (keyframe poses, pair statistics, the MILD database)
and exposes the phases of one keyframe's insertion: :meth:`Optimizer.begin` (add the keyframe
and its odometry pair, query MILD), :meth:`Optimizer.optimized` (take the keyframe's FastGO
result, where it ran: before a loop test, or after every keyframe with
``fastgo_every_keyframe``) and :meth:`Optimizer.close_loops` (register, test and accept loop
candidates, §IV-C).
The FastGO call between them is made by ``system.insert_keyframes``, for one optimiser or for
several sequences at once. A :class:`Worker` runs insertions in a background thread, inline,
or leaves them for the lockstep driver (deferred); a :class:`ProcessWorker` runs them in a
child process.

Why a process: the optimiser's work (MILD, loop registration, FastGO) and the tracker's are
both made of many small tensor operations, each of which takes and releases Python's global
interpreter lock. Two such threads hand the lock back and forth and run no faster together
than one after the other (often slower), so on the CPU the background thread bought no
overlap. A child process has its own interpreter: tracking and optimisation then run on two
cores at once, with the same results.
"""

from __future__ import annotations

import logging
import multiprocessing
import pickle
import queue
import signal
import threading
import time
import traceback
import weakref
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ...devices import is_host
from ...errors import TorchSlamError
from ...fastgo import FastGOConfig, FastGOProblem, PairStats, accept_loop_closures, optimize
from ...loop import MILDDatabase
from ...registration.dense import DenseFrame, DenseImages, register_dense_frames
from ...registration.rolling import dense_images_at_stamp
from ...registration.sparse import FrameFeatures, register_sparse_batch
from ...threads import name_os_thread
from .. import pickling as messages
from ..base import add_stage_ms
from ..monitor import Monitor
from .config import GCSlamConfig

__all__ = ["Anchor", "KeyframeEvent", "Optimizer", "ProcessWorker", "Worker", "make_worker"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Anchor:
    """Where an unlinked keyframe starts: the last tracked frame's keyframe and pose relative to it."""

    kf: int  # keyframe id of the last tracked frame
    T_kf: Tensor  # (4, 4) float64 that frame's pose in keyframe ``kf``, p_kf = T p_frame


@dataclass
class KeyframeEvent:
    """What the tracker hands the optimiser for one new keyframe."""

    kf: int  # keyframe id (0, 1, ...)
    reference: int | None  # keyframe it was registered to, None for an unlinked keyframe
    T_ref_kf: Tensor | None  # (4, 4) float64 relative pose, p_ref = T p_kf
    stats: PairStats | None  # statistics of that registration's correspondences
    features: FrameFeatures  # ORB features of the keyframe (for MILD and loop registration)
    anchor: Anchor | None = None  # unlinked keyframe only: the last tracked frame
    frame_index: int = 0  # the keyframe's sequence frame index (the TensorBoard step)
    promoted: bool = False  # made from the previous frame of a weak one (``keyframe_weak_ratio``)
    images: DenseImages | None = None  # working images of the keyframe where pairs are registered densely (``keyframe_pairs``)
    refine: bool = False  # its odometry pair came from ORB features and is registered again densely
    # readout_time: ``images`` are as read and are resampled to the keyframe's stamp here with this
    # (twist (6,), readout seconds) before any use (the sparse front-end's keyframes: off the tracker's path)
    images_motion: tuple[Tensor, float] | None = None


# Keyframe pyramids kept built for dense pair registration (about 6 MB each at 320x240); the
# other keyframes keep only their working images and are rebuilt when a loop needs them.
_PYRAMID_CACHE = 8


class Optimizer:
    """Keyframe poses, pairs, the MILD database and FastGO: the optimisation thread's state.

    Poses and pair statistics live on the CPU in float64 whatever device the front-end uses
    (FastGO's cost does not grow with images, and float64 is the back-end's precision).

    With ``cfg.dense_pairs`` every keyframe's working images are kept (``images``), and a pair
    registered from ORB features (the event's odometry pair where ``refine`` says so, every
    loop) is registered again densely from that pose: the dense correspondences' statistics
    replace the ORB ones where that succeeds (``refined`` counts both outcomes).
    """

    def __init__(self, cfg: GCSlamConfig, monitor: Monitor) -> None:
        self.cfg = cfg
        self.monitor = monitor
        self.T_wk: list[Tensor] = []
        self.pairs: list[tuple[int, int]] = []
        self.stats: list[PairStats] = []
        self.pair_kind: list[str] = []  # "odometry" (tracked or relocalised keyframe) or "loop"
        self.features: list[FrameFeatures] = []
        self.images: list[DenseImages | None] = []
        self._pyramids: OrderedDict[int, DenseFrame] = OrderedDict()
        self.refined = {"odometry": 0, "loops": 0, "failed": 0}
        self.mild = MILDDatabase(cfg.mild)
        self.loops = {"candidates": 0, "registered": 0, "accepted": 0, "rejected": 0}
        self.stage_ms: dict[str, float] = {}
        self.fastgo_ms: list[float] = []
        self.generator = torch.Generator().manual_seed(cfg.sparse.seed + 1)

    def _add_ms(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    def fastgo_config(self, iterations: int) -> FastGOConfig:
        """FastGO's settings for a run of ``iterations``."""
        return FastGOConfig(iterations=iterations)

    def problem(self) -> FastGOProblem:
        """The pose graph as it stands: all keyframes, all pairs, keyframe 0 fixed."""
        T = torch.stack(self.T_wk)
        if not self.pairs:
            return FastGOProblem(T, torch.zeros(0, 2, dtype=torch.int64), PairStats.empty(0), 0)
        return FastGOProblem(T, torch.tensor(self.pairs, dtype=torch.int64), PairStats.cat(self.stats), 0)

    def begin(self, ev: KeyframeEvent) -> list[int]:
        """Add the keyframe and its odometry pair; query and update MILD; return loop candidates."""
        cfg = self.cfg
        if ev.kf != len(self.T_wk):
            raise TorchSlamError(f"keyframe {ev.kf} inserted out of order (expected {len(self.T_wk)})")
        if ev.reference is None:
            # An unlinked keyframe starts where the last tracked frame was; that guess only
            # matters until a loop closure links it to the rest.
            T0 = torch.eye(4, dtype=torch.float64)
            if ev.anchor is not None:
                T0 = self.T_wk[ev.anchor.kf] @ ev.anchor.T_kf.to(torch.float64)
            self.T_wk.append(T0)
        self.features.append(ev.features)
        images = ev.images if cfg.dense_pairs else None
        if images is not None and ev.images_motion is not None:
            twist, readout = ev.images_motion
            images = dense_images_at_stamp(images, twist.to(images.grey.dtype), readout)
        self.images.append(images)
        if ev.reference is not None:
            T_ref_kf, stats = ev.T_ref_kf.to(torch.float64), ev.stats.to("cpu", torch.float64)
            if ev.refine:
                t0 = time.perf_counter()
                (measured,) = self.measure_densely([ev.reference], ev.kf, T_ref_kf[None], "odometry")
                if measured is not None:
                    T_ref_kf, stats = measured
                self._add_ms("pair_refinement", t0)
            self.T_wk.append(self.T_wk[ev.reference] @ T_ref_kf)
            self.pairs.append((ev.reference, ev.kf))
            self.stats.append(stats)
            self.pair_kind.append("odometry")
        t0 = time.perf_counter()
        candidates: list[int] = []
        # A promoted keyframe lies a frame or two after the keyframe before it, whose loops (and
        # the next keyframe's) cover its place: it joins MILD but proposes no loops of its own.
        if cfg.loops and len(self.mild) and not ev.promoted:
            ids, _ = self.mild.query(ev.features.descriptors)
            candidates = [int(c) for c in ids if int(c) != ev.reference]
        self.mild.add(ev.kf, ev.features.descriptors)
        self._add_ms("loop_detection", t0)
        return candidates

    def _pyramid(self, k: int) -> DenseFrame:
        """Keyframe ``k``'s dense pyramid, built from its images on first use (a few kept)."""
        pyr = self._pyramids.get(k)
        if pyr is None:
            pyr = self._pyramids[k] = self.images[k].pyramid()
            if len(self._pyramids) > _PYRAMID_CACHE:
                self._pyramids.popitem(last=False)
        self._pyramids.move_to_end(k)
        return pyr

    def measure_densely(self, refs: list[int], kf: int, T_init: Tensor, kind: str) -> list[tuple[Tensor, PairStats] | None]:
        """Register keyframe ``kf`` densely to each of the keyframes ``refs`` from ``T_init`` (R, 4, 4), ``p_ref = T p_kf``.

        Returns per pair its float64 CPU pose and statistics, or None where it is not measured
        densely (a keyframe without images) or the registration failed; successes are counted
        in ``refined[kind]``, failures in ``refined["failed"]``.
        """
        if not all(k < len(self.images) and self.images[k] is not None for k in refs + [kf]):
            return [None] * len(refs)
        fj = self._pyramid(kf)
        T = T_init.to(fj.levels[0].grey.device, torch.float64)
        if is_host(T):
            # The host registers B pairs one by one anyway (``registration.dense``): each pair
            # against its cached pyramid, whose reference channels are then built once and kept,
            # instead of a concatenated copy of the pyramids.
            parts = [(register_dense_frames(self._pyramid(r), fj, T[k], self.cfg.dense), 0) for k, r in enumerate(refs)]
        else:
            res = register_dense_frames(DenseFrame.cat([self._pyramid(r) for r in refs]), fj.expand(len(refs)), T, self.cfg.dense)
            parts = [(res, k) for k in range(len(refs))]
        out: list[tuple[Tensor, PairStats] | None] = []
        for res, k in parts:
            ok = bool(res.success[k])
            self.refined[kind if ok else "failed"] += 1
            out.append((res.T_ij[k].to("cpu", torch.float64), res.stats[torch.tensor([k], device=res.stats.device)].to("cpu", torch.float64))
                       if ok else None)
        return out

    def optimized(self, res, frame_index: int, ms: float) -> None:
        """Take the result of the per-keyframe FastGO run (``ms``: its share of the time)."""
        self.T_wk = list(res.T_wc.unbind(0))
        self.fastgo_ms.append(ms)
        self.stage_ms["fastgo"] = self.stage_ms.get("fastgo", 0.0) + ms
        self.monitor.scalar("optimization/fastgo_ms", ms, frame_index)

    def close_loops(self, kf: int, candidates: list[int], frame_index: int = 0) -> None:
        """Register the candidates to keyframe ``kf`` and keep the loops that pass the test of §IV-C."""
        cfg = self.cfg
        t0 = time.perf_counter()
        self.loops["candidates"] += len(candidates)
        # Brute-force matching: a loop is a measurement independent of the pose graph. Matches
        # guided by the graph's relative pose (as tracking's are) were tried and confirm the
        # drift instead of measuring it (7-Scenes, dense front-end: 1.84 -> 2.24 cm).
        res = register_sparse_batch([self.features[c] for c in candidates], [self.features[kf]] * len(candidates), cfg.sparse, self.generator)
        ok = [b for b in range(len(candidates)) if bool(res.success[b])]
        t0 = self._add_ms("loop_registration", t0)
        if not ok:
            return
        self.loops["registered"] += len(ok)
        pair_stats = {b: res.stats[torch.tensor([b], device=res.stats.device)].to("cpu", torch.float64) for b in ok}
        if cfg.dense_pairs:
            # Each verified loop measured again densely from its ORB pose; a failure keeps the ORB one.
            for b, m in zip(ok, self.measure_densely([candidates[b] for b in ok], kf, res.T_ij[ok], "loops")):
                if m is not None:
                    # The dense pose; with ``loop_pair_weight`` orb, the ORB pair's total weight.
                    pair_stats[b] = m[1].weighted(pair_stats[b].n / m[1].n) if cfg.loops_at_orb_weight else m[1]
            t0 = self._add_ms("pair_refinement", t0)
        # All verified candidates are tested together; if that is rejected, each on its own, so
        # one false candidate does not take the true ones down with it.
        trials = [ok] if len(ok) == 1 else [ok] + [[b] for b in ok]
        for k, group in enumerate(trials):
            p = self.problem()
            loop_pairs = torch.tensor([(candidates[b], kf) for b in group], dtype=torch.int64)
            loop_stats = PairStats.cat([pair_stats[b] for b in group])
            decision = accept_loop_closures(
                p.T_wc, p.pairs, p.stats, loop_pairs, loop_stats, fixed=0, threshold=float("inf"),
                config=self.fastgo_config(cfg.loop_iterations),
            )
            rms_before, rms_after = decision.cost_before**0.5, decision.cost_after**0.5
            accepted = rms_after <= rms_before * (1.0 + cfg.loop_threshold) + cfg.loop_slack_m
            if accepted:
                self.T_wk = list(decision.result.T_wc.unbind(0))
                for b in group:
                    self.pairs.append((candidates[b], kf))
                    self.pair_kind.append("loop")
                self.stats.append(loop_stats)
                self.loops["accepted"] += len(group)
                self.monitor.scalar("progress/loops_accepted", self.loops["accepted"], frame_index)
                logger.debug("keyframe %d: loop(s) to %s accepted (RMS %.4f -> %.4f m)", kf, [candidates[b] for b in group],
                             rms_before, rms_after)
                if k == 0:
                    break
            else:
                if k > 0 or len(group) == 1:
                    self.loops["rejected"] += len(group)
        self._add_ms("loop_acceptance", t0)

    def finish(self) -> None:
        """One last FastGO run of ``final_iterations`` over all keyframes."""
        if self.cfg.final_iterations and self.pairs:
            t0 = time.perf_counter()
            p = self.problem()
            res = optimize(p.T_wc, p.pairs, p.stats, fixed=0, config=self.fastgo_config(self.cfg.final_iterations))
            self.T_wk = list(res.T_wc.unbind(0))
            self._add_ms("fastgo_final", t0)


class Worker:
    """Runs the insertion of new keyframes into an :class:`Optimizer` in a background thread, inline, or deferred.

    Deferred (lockstep runs of several sequences): new keyframes wait in ``pending`` until the
    driver inserts those of all sequences together (``system.track_frames``).
    """

    def __init__(
        self, optimizer: Optimizer, insert: Callable[[Optimizer, KeyframeEvent], None], threaded: bool, deferred: bool = False
    ) -> None:
        """
        Args:
            optimizer: the optimiser the keyframes go to.
            insert: inserts one keyframe into one optimiser (``system.insert_keyframe``).
            threaded: insert in a background thread.
            deferred: keep new keyframes in ``pending``; overrides ``threaded``.
        """
        self.optimizer = optimizer
        self._insert = insert
        self.threaded = threaded and not deferred
        self.deferred = deferred
        self.pending: list[KeyframeEvent] = []
        self.error: BaseException | None = None
        if self.threaded:
            self.queue: queue.Queue = queue.Queue()
            self.thread = threading.Thread(target=self._loop, name="torchslam-gcslam-optimizer", daemon=True)
            self.thread.start()

    def _loop(self) -> None:
        name_os_thread("tslam-optimizer")
        while True:
            ev = self.queue.get()
            if ev is None:
                return
            if self.error is not None:
                continue
            try:
                self._insert(self.optimizer, ev)
            except BaseException as exc:  # noqa: BLE001 - reported to the tracking thread at the next call
                self.error = exc

    @property
    def background(self) -> str:
        """Where the insertions run: ``"deferred"`` (lockstep), ``"thread"`` or ``"inline"``."""
        return "deferred" if self.deferred else "thread" if self.threaded else "inline"

    def refresh(self) -> None:
        """Nothing to take: the thread and inline insertion update the optimiser in place."""

    def submit(self, ev: KeyframeEvent) -> None:
        """Hand over one new keyframe; raises if the background thread has failed."""
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error
        if self.threaded:
            self.queue.put(ev)
        elif self.deferred:
            self.pending.append(ev)
        else:
            self._insert(self.optimizer, ev)

    def join(self) -> None:
        """Insert what is pending, stop the thread and raise its error, if any."""
        while self.pending:
            self._insert(self.optimizer, self.pending.pop(0))
        if self.threaded:
            self.queue.put(None)
            self.thread.join()
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error


# What the optimisation process sends back of its optimiser: after every keyframe the poses and
# counters (for the progress of a run), at the end everything ``finish`` and the metrics read.
_PROGRESS_FIELDS = ("T_wk", "loops", "refined")
_FINAL_FIELDS = _PROGRESS_FIELDS + ("pairs", "stats", "pair_kind", "stage_ms", "fastgo_ms")


class _ScalarLog(Monitor):
    """The child's monitor: keeps the optimiser's scalars for the parent to write."""

    def __init__(self) -> None:
        self.pending: list[tuple[str, float, int]] = []

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.pending.append((tag, float(value), int(step)))


def _read_events(conn, inbox: queue.Queue) -> None:
    """The child's reader thread: keyframe events into ``inbox`` as they arrive, then None."""
    name_os_thread("tslam-opt-inbox")
    try:
        while True:
            ev = messages.loads(conn.recv_bytes())
            inbox.put(ev)
            if ev is None:
                return
    except (EOFError, OSError):
        inbox.put(None)  # the parent has gone: finish what was received


def _serve(conn, optimizer: Optimizer, insert: Callable[[Optimizer, KeyframeEvent], None]) -> None:
    """The optimisation process: insert each keyframe event received, answer with the progress.

    A reader thread takes the events off the pipe as they come, so the parent never waits on a
    full pipe while this process optimises. Messages are pickled by value (``send_bytes``), not
    through shared memory: they are small (one keyframe's features, the poses) and few. Their
    tensors travel as NumPy arrays (``systems.pickling``): torch's own pickling cost 3.7 ms per
    keyframe event and grew with the poses sent back after every keyframe.
    """
    # Ctrl-C reaches the whole process group: the parent stops tracking and joins, and the child
    # finishes the keyframes it was given.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    name_os_thread("tslam-optimizer")
    torch.set_num_threads(1)  # small operations only; and the parent's thread pool is not inherited
    log = _ScalarLog()
    optimizer.monitor = log
    inbox: queue.Queue = queue.Queue()
    threading.Thread(target=_read_events, args=(conn, inbox), name="torchslam-optimizer-inbox", daemon=True).start()
    try:
        while True:
            ev = inbox.get()
            if ev is None:
                state = {f: getattr(optimizer, f) for f in _FINAL_FIELDS}
                conn.send_bytes(messages.dumps(("final", state, log.pending)))
                return
            insert(optimizer, ev)
            state = {f: getattr(optimizer, f) for f in _PROGRESS_FIELDS}
            conn.send_bytes(messages.dumps(("progress", state, log.pending)))
            log.pending = []
    except BaseException:  # noqa: BLE001 - reported to the parent, which raises it
        try:
            conn.send_bytes(pickle.dumps(("error", traceback.format_exc(), [])))
        except (OSError, ValueError):
            pass  # the parent has gone


def _receive(conn, process, inbox: queue.Queue) -> None:
    """The parent's receiver thread: the child's messages into ``inbox`` until its last one."""
    name_os_thread("tslam-opt-recv")
    while True:
        try:
            msg = messages.loads(conn.recv_bytes())
        except (EOFError, OSError):
            process.join(timeout=5)
            msg = ("error", f"the process ended unexpectedly (exit code {process.exitcode})", [])
        inbox.put(msg)
        if msg[0] != "progress":
            return


def _send_end(conn) -> None:
    """Tell the optimisation process that no keyframe follows (it answers with its final state)."""
    try:
        conn.send_bytes(pickle.dumps(None))
    except OSError:
        pass  # the child has gone; the receiver reports how


class ProcessWorker:
    """Runs the insertion of new keyframes into an :class:`Optimizer` in a child process.

    The parent's ``optimizer`` is a mirror: its poses and loop counters follow the child's after
    each keyframe (taken when the tracker submits the next one or calls :meth:`refresh`), and
    :meth:`join` copies everything else back (pairs, statistics, stage times), so the tracker
    reads the optimiser exactly as with the thread. The child is forked (no second import of
    torch) and runs one torch thread; the front-end's tensors must be on the CPU. A thread of
    the parent's receives the child's messages as they come (waiting on the pipe outside the
    interpreter lock), so neither side ever blocks on a full pipe.
    """

    threaded = True
    background = "process"

    def __init__(self, optimizer: Optimizer, insert: Callable[[Optimizer, KeyframeEvent], None]) -> None:
        """
        Args:
            optimizer: the optimiser the keyframes go to (the child works on a copy of it).
            insert: inserts one keyframe into one optimiser (``system.insert_keyframe``).
        """
        self.optimizer = optimizer
        self.error: BaseException | None = None
        self._done = False
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_serve, args=(child, optimizer, insert), name="torchslam-gcslam-optimizer",
                                   daemon=True)
        self.process.start()
        child.close()
        self._inbox: queue.Queue = queue.Queue()
        # The receiver holds no reference to this worker, so a worker dropped without join (a
        # run that failed mid-sequence) is collected; its finaliser then lets the child finish
        # and exit instead of waiting for keyframes for ever.
        self._receiver = threading.Thread(target=_receive, args=(self._conn, self.process, self._inbox),
                                          name="torchslam-gcslam-optimizer-inbox", daemon=True)
        self._receiver.start()
        self._release = weakref.finalize(self, _send_end, self._conn)

    def _apply(self, msg) -> None:
        kind, payload, scalars = msg
        if kind == "error":
            self.error = TorchSlamError(payload)
            self._done = True
            return
        for name, value in payload.items():
            setattr(self.optimizer, name, value)
        for tag, value, step in scalars:
            self.optimizer.monitor.scalar(tag, value, step)
        self._done = kind == "final"

    def refresh(self) -> None:
        """Take the progress the child has reported so far (poses, loop counters, scalars)."""
        while True:
            try:
                msg = self._inbox.get_nowait()
            except queue.Empty:
                return
            self._apply(msg)

    def _raise(self) -> None:
        raise TorchSlamError(f"GC-SLAM optimisation process failed: {self.error}") from self.error

    def submit(self, ev: KeyframeEvent) -> None:
        """Hand over one new keyframe; raises if the child has failed."""
        self.refresh()
        if self.error is not None:
            self._raise()
        if ev.features.points.device.type != "cpu":
            raise TorchSlamError("GC-SLAM optimisation process: keyframe features must be on the CPU")
        self._conn.send_bytes(messages.dumps(ev))

    def join(self) -> None:
        """Wait for the keyframes still queued, copy the child's optimiser back and end the child."""
        self.refresh()
        self._release.detach()
        if not self._done:
            _send_end(self._conn)
            while not self._done:
                self._apply(self._inbox.get())
        self._receiver.join()
        self._conn.close()
        self.process.join()
        if self.error is not None:
            self._raise()


def make_worker(
    optimizer: Optimizer, insert: Callable[[Optimizer, KeyframeEvent], None], cfg, device: torch.device, deferred: bool
) -> Worker | ProcessWorker:
    """The worker ``cfg`` asks for: deferred, inline, a thread, or a child process.

    The process (``cfg.background == "process"``) needs the fork start method, a CPU front-end
    and a process that may have children; elsewhere (macOS, Windows, an accelerator, a daemonic
    process such as a ``multiprocessing.Pool`` worker) the thread runs instead.
    """
    if (
        cfg.threaded and not deferred and cfg.background == "process" and device.type == "cpu"
        and "fork" in multiprocessing.get_all_start_methods() and not multiprocessing.current_process().daemon
    ):
        return ProcessWorker(optimizer, insert)
    return Worker(optimizer, insert, cfg.threaded, deferred=deferred)
