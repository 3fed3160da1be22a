"""What every SLAM system provides, and the one loop that drives systems over sequences.

A system is fed frames one at a time (``track``) and returns everything it estimated at the end
(``finish``). The driver (``drive``; ``run_sequence`` is its B = 1 case, ``lockstep.run_lockstep``
its many-sequence front) measures time spent waiting for frames (decode) separately from time
spent inside the systems (compute), turns Ctrl-C into a clean stop that keeps what was computed,
and counts frames that the sequences had to skip.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from ..data.frame import Frame, Sequence
from ..data.trajectory import Trajectory
from ..errors import ConfigError
from ..threads import name_os_thread
from .ahead_process import ProcessSource
from .ahead_process import available as process_available
from .memory import check_run_memory

__all__ = [
    "AheadFrames", "AheadResults", "RunResult", "SlamSystem", "StepReport", "SystemOutput", "check_max_frames", "drive", "empty_output",
    "frame_poses", "resample_poses", "run_sequence", "track_each",
]

logger = logging.getLogger(__name__)


@dataclass
class SystemOutput:
    """Everything a system estimated over one sequence.

    Convention:
        Every pose and map point is in one world frame, the same for both systems: the camera
        frame of the first keyframe at its depth instant (x right, y down, z forward, metres),
        so ``keyframe_T_wc[0]`` is the identity, and ``map_points`` line up with ``T_wc``.

    Attributes:
        frame_indices: (N,) int64 indices (into the sequence) of the frames that have a pose.
        timestamps: (N,) float64 seconds of those frames.
        T_wc: (N, 4, 4) float64 estimated camera-to-world poses, after the final optimisation.
        keyframe_indices: (K,) int64 sequence indices of the keyframes.
        keyframe_T_wc: (K, 4, 4) float64 keyframe poses.
        map_points: optional (P, 3) float32 world points of the map, metres.
        map_colors: optional (P, 3) float32 colours in [0, 1].
        stage_ms: total milliseconds spent in each named stage.
        metrics: system-specific figures (loops, PSR statistics, attitude source, ...).
        prior_indices: (M,) int64 sequence indices of the frames among ``frame_indices`` whose
            pose is a motion prior, not an estimate from their own data (GC-SLAM's lost frames
            holding the last pose and unlinked keyframes started there, NI-SLAM's frames on the
            constant-velocity prediction); None = none.
    """

    frame_indices: Tensor
    timestamps: Tensor
    T_wc: Tensor
    keyframe_indices: Tensor
    keyframe_T_wc: Tensor
    map_points: Tensor | None = None
    map_colors: Tensor | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    prior_indices: Tensor | None = None


class SlamSystem(Protocol):
    """Interface of a SLAM system as the driver and the application's monitoring see it.

    ``start``, ``track`` and ``finish`` drive a run. A system whose ``prepares_ahead`` is true
    also has ``prepare_ahead(frame)``: the per-frame work that depends on the frame alone (and on
    what ``start`` set up), which ``run_sequence`` runs on a thread of its own a frame or two
    before ``track`` (:class:`AheadFrames`), so that it overlaps the tracking of the frames before.
    ``stage_ms``, ``last_frame_index``,
    ``estimate_so_far`` and ``progress_counters`` are read between frames for live monitoring
    (``app.progress``); a class that inherits from ``SlamSystem`` gets the defaults documented
    below and logs only its stage times.

    Attributes:
        name: the system's registry name.
        stage_ms: running total milliseconds per named stage over the current sequence.
        last_frame_index: ``Frame.index`` of the frame last given to ``track`` (the step of
            every live figure), or None before the first (default).
    """

    name: str
    stage_ms: dict[str, float]
    last_frame_index: int | None = None
    prepares_ahead: bool = False

    def start(self, sequence: Sequence) -> None:
        """Prepare for a new sequence (camera, attitude stream, ...)."""

    def track(self, frame: Frame) -> None:
        """Process one frame."""

    def finish(self) -> SystemOutput:
        """Run any final optimisation and return the estimates."""

    def estimate_so_far(self) -> Trajectory | None:
        """The trajectory of the frames processed so far in the system's current estimate, at
        their depth instants, or None where there is none yet (default: None, no live ATE)."""
        return None

    def progress_counters(self) -> dict[str, float]:
        """Counters for live monitoring (keyframes, loops, lost frames, ...) by name (default: none)."""
        return {}


@dataclass
class RunResult:
    """A system's output plus how the run went."""

    output: SystemOutput
    frames_total: int
    frames_processed: int
    frames_skipped: int
    skipped: list[tuple[int, str]]
    wall_s: float
    compute_s: float
    interrupted: bool

    @classmethod
    def of(cls, sequence, output: SystemOutput, processed: int, wall_s: float, compute_s: float, interrupted: bool) -> "RunResult":
        """The result of a run over ``sequence``; the frames it skipped come from the sequence."""
        skipped = list(getattr(sequence, "skipped", []))
        return cls(
            output=output, frames_total=len(sequence), frames_processed=processed, frames_skipped=len(skipped),
            skipped=skipped, wall_s=wall_s, compute_s=compute_s, interrupted=interrupted,
        )

    @property
    def fps_end_to_end(self) -> float:
        return self.frames_processed / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def fps_compute(self) -> float:
        return self.frames_processed / self.compute_s if self.compute_s > 0 else 0.0


def check_max_frames(value: Any, name: str = "--max-frames") -> int | None:
    """Validate a frame limit of ``run`` or ``batch``: None (all frames) or an integer >= 1.

    Raises:
        ConfigError: naming ``name`` for 0, a negative number or a non-integer.
    """
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        raise ConfigError(f"{name}: expected an integer >= 1, got {value!r}")
    return value


def run_sequence(
    system: SlamSystem,
    sequence: Sequence,
    progress: Callable[[Iterable[Frame]], Iterable[Frame]] | None = None,
    max_frames: int | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> RunResult:
    """Drive ``system`` over ``sequence`` and return its output and timings: ``drive`` with B = 1.

    A system that ``prepares_ahead`` has each frame prepared on a thread of its own while it
    tracks the frames before (``drive``'s ``ahead``).

    Ctrl-C (``KeyboardInterrupt``) stops the loop; the system is still asked to ``finish`` so
    the frames processed so far are returned with ``interrupted=True``.

    Args:
        system: the SLAM system (not started).
        sequence: frames to process, in order.
        progress: optional wrapper around the frame iterator (e.g. a progress bar).
        max_frames: stop after this many frames.
        on_frame: called with the number of frames processed so far after each frame, outside
            the compute timer (monitoring: e.g. the ATE so far every n frames).

    Raises:
        InsufficientMemoryError: before the first frame is read, when the configuration's
            estimated memory exceeds the device's (``systems.memory``).
        Whatever the system's ``start``, ``track`` or ``finish``, or reading a frame, raised.
    """
    (result,) = drive(
        [system], [sequence], track_each, progress=progress, max_frames=max_frames,
        on_frame=None if on_frame is None else (lambda i, n: on_frame(n)), ahead=True,
    )
    if isinstance(result, BaseException):
        raise result
    return result


def track_each(systems: list[SlamSystem], frames: list[Frame], max_batch: int | None = None) -> StepReport:
    """The step of a system with no batched step: ``track`` of one system after the other."""
    errors: list[Exception | None] = [None] * len(systems)
    seconds = [0.0] * len(systems)
    for k, (system, frame) in enumerate(zip(systems, frames)):
        t0 = time.perf_counter()
        try:
            system.track(frame)
        except Exception as exc:  # noqa: BLE001 - reported in the sequence's place
            errors[k] = exc
        seconds[k] = time.perf_counter() - t0
    return StepReport(errors=errors, compute_s=seconds)


def drive(
    systems: list[SlamSystem],
    sequences: list[Sequence],
    step: Callable[[list, list[Frame], int | None], StepReport],
    max_batch: int | None = None,
    progress: Callable[[Iterable[Frame]], Iterable[Frame]] | None = None,
    max_frames: int | None = None,
    on_frame: Callable[[int, int], None] | None = None,
    memory_batch: int = 1,
    ahead: bool = False,
) -> list[RunResult | BaseException]:
    """The one driver: run built systems over their sequences, one frame of each per step.

    In order: the memory check (before any frame is read), ``start`` of every system, then steps
    of ``step(systems, frames, max_batch)`` over the systems that still have frames, each system
    finished as its sequence runs out (which frees its state), and ``RunResult``s built with the
    frames the sequences skipped. A sequence whose start, frame read, step or finish raises is
    returned as that exception; the others go on. Ctrl-C stops every sequence, finishes each
    with what it has computed and marks it ``interrupted``.

    Timing:
        ``wall_s`` of every result is the group's wall-clock time, from the start of the first
        sequence to the last finish: the frames of all sequences were interleaved, so no shorter
        span belongs to one of them (``fps_end_to_end`` is thus a sequence's share of the group).
        ``compute_s`` is a sequence's own work (``start``, its part of every step, ``finish``):
        in a batched step its own phases plus an equal share of each batched call it took part
        in (``StepReport.compute_s``). Time spent waiting for frames (decode) and in ``on_frame``
        is in neither share but is in ``wall_s``.

    Args:
        systems: one built, not started system per sequence.
        sequences: the sequences.
        step: advances started systems by one frame each (``track_each``, or a system's batched
            step such as ``nislam.track_frames``).
        max_batch: passed to ``step``.
        progress: wrapper around each sequence's frame iterator (e.g. a progress bar).
        max_frames: stop each sequence after this many frames.
        on_frame: ``on_frame(i, processed)`` after each frame of sequence ``i``, outside the timers.
        memory_batch: sequences whose state the memory check counts at once.
        ahead: give every system that ``prepares_ahead`` its frames through :class:`AheadFrames`
            (one thread per sequence, so meant for few sequences: ``run_sequence``). Its seconds
            count in the sequence's ``compute_s``.

    Returns:
        Per sequence, in order, its ``RunResult`` or the exception that stopped it.

    Raises:
        InsufficientMemoryError: the configuration needs more memory than the device has.
    """
    n = len(sequences)
    check_run_memory(systems[0], [getattr(s, "camera", None) for s in sequences], batch=memory_batch)
    live: list[SlamSystem | None] = list(systems)
    failed: list[BaseException | None] = [None] * n
    outputs: list[SystemOutput | None] = [None] * n
    frames_in: list[Iterator[Frame] | None] = [None] * n
    aheads: list[AheadFrames | None] = [None] * n
    processed = [0] * n
    compute = [0.0] * n
    interrupted = False
    t_start = time.perf_counter()

    def finish(i: int) -> None:
        t0 = time.perf_counter()
        try:
            outputs[i] = live[i].finish()
        except Exception as exc:  # noqa: BLE001 - reported in the sequence's place
            failed[i] = exc
            logger.warning("%s: finish failed: %s", sequences[i].name, exc)
        live[i] = None  # its state is no longer needed
        compute[i] += time.perf_counter() - t0

    active: list[int] = []
    try:
        for i, seq in enumerate(sequences):
            t0 = time.perf_counter()
            try:
                frames: Iterable[Frame] = iter(seq)
                if ahead and getattr(live[i], "prepares_ahead", False):
                    frames = aheads[i] = AheadFrames(live[i], frames, sequence=seq)
                if progress is not None:
                    frames = progress(frames)
                frames_in[i] = iter(frames)
                live[i].start(seq)
                active.append(i)
            except Exception as exc:  # noqa: BLE001 - reported in the sequence's place
                failed[i] = exc
                logger.warning("%s: start failed: %s", seq.name, exc)
            compute[i] += time.perf_counter() - t0
        while active:
            stepping, frames_now = [], []
            for i in active:
                frame = None
                if max_frames is None or processed[i] < max_frames:
                    try:
                        frame = next(frames_in[i])
                        if aheads[i] is not None:
                            compute[i] += aheads[i].take_seconds()
                    except StopIteration:
                        pass
                    except Exception as exc:  # noqa: BLE001 - a sequence that cannot be read stops alone
                        failed[i] = exc
                        logger.warning("%s: reading frame %d failed: %s", sequences[i].name, processed[i], exc)
                        continue
                if frame is None:
                    finish(i)
                else:
                    stepping.append(i)
                    frames_now.append(frame)
            if not stepping:
                break
            report = step([live[i] for i in stepping], frames_now, max_batch)
            for k, i in enumerate(stepping):
                compute[i] += report.compute_s[k]
                if report.errors[k] is not None:
                    failed[i] = report.errors[k]
                    live[i] = None
                    logger.warning("%s: frame %d failed: %s", sequences[i].name, frames_now[k].index, report.errors[k])
                else:
                    processed[i] += 1
                    if on_frame is not None:
                        on_frame(i, processed[i])
            active = [i for i in stepping if failed[i] is None]
    except KeyboardInterrupt:
        interrupted = True
        logger.warning("interrupted; finishing every sequence with what was computed")
    for i in range(n):
        if failed[i] is None and outputs[i] is None and live[i] is not None and frames_in[i] is not None:
            finish(i)
    for a in aheads:
        if a is not None:
            a.close()
    wall_s = time.perf_counter() - t_start

    results: list[RunResult | BaseException] = []
    for i, seq in enumerate(sequences):
        if failed[i] is not None:
            results.append(failed[i])
            continue
        # Only a Ctrl-C before its start leaves a sequence without output: it computed nothing.
        output = outputs[i] if outputs[i] is not None else empty_output()
        results.append(RunResult.of(seq, output, processed[i], wall_s, compute[i], interrupted))
    return results


class AheadFrames:
    """Frames of a sequence, each passed through ``system.prepare_ahead`` on a background thread.

    The thread reads the frames (from ``frames``, which may decode ahead itself) and prepares
    each while the consumer tracks the ones before, at most ``depth`` frames ahead. A frame is
    handed out only once its preparation has finished, so ``track`` finds it done. What the
    preparation computes depends on the frame alone, so a run gives the same results with or
    without this (tested); it only overlaps the work with tracking where a core is free.

    An error while reading a frame is raised by ``next`` in the frame's place, as the plain
    iterator would raise it. An error inside ``prepare_ahead`` is not raised here: the frame is
    handed out unprepared and ``track`` prepares it inline, raising it there, in the frame's
    place. :meth:`close` stops the thread (``drive`` calls it once the sequences are done).

    A system whose ``prepares_ahead_in_process`` is true (after its ``start``) has its frames
    read and prepared in a forked child process instead, where fork is available
    (:mod:`~torchslam.systems.ahead_process`): its ``ahead_payload(frame)`` returns what
    ``prepare_ahead`` computes and its stage times, ``accept_ahead(frame, payload, stage_ms)``
    stores them for ``track``. The reading and the preparation then share no interpreter lock
    with tracking. ``sequence``: where the child's reading skipped frames, they are added to
    ``sequence.skipped`` here as the reading in this process adds them.
    """

    def __init__(self, system: SlamSystem, frames: Iterable[Frame], depth: int = 2, sequence: Sequence | None = None) -> None:
        if not (isinstance(depth, int) and depth >= 1):
            raise ConfigError(f"depth: expected an integer >= 1, got {depth!r}")
        self.system = system
        self.sequence = sequence
        self._source = iter(frames)
        self._process: ProcessSource | None = None
        self._slots = threading.Semaphore(depth)
        self._results: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seconds = 0.0
        self._done = False

    def __iter__(self) -> AheadFrames:
        return self

    def __next__(self) -> Frame:
        if self._done:
            raise StopIteration
        if self._thread is None and self._process is None:  # started on the first frame, after the system's start
            if getattr(self.system, "prepares_ahead_in_process", False) and process_available():
                self._process = ProcessSource(self.system, self._source, self.sequence)
            else:
                self._thread = threading.Thread(target=self._work, name="torchslam-ahead", daemon=True)
                self._thread.start()
        if self._process is not None:
            kind, value, seconds = self._process.next()
        else:
            kind, value, seconds = self._results.get()
            self._slots.release()
        if kind == "frame":
            self._seconds += seconds
            return value
        self._done = True
        self._join()
        if kind == "error":
            raise value
        raise StopIteration

    def take_seconds(self) -> float:
        """Seconds spent in ``prepare_ahead`` for the frames handed out since the last call."""
        s, self._seconds = self._seconds, 0.0
        return s

    def close(self) -> None:
        """Stop the thread (frames it prepared and nobody took are dropped)."""
        self._done = True
        self._stop.set()
        self._join()

    def _join(self) -> None:
        if self._process is not None:
            self._process.close()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        close = getattr(self._source, "close", None)
        if close is not None:  # a generator's own prefetch thread stops with it
            close()

    def _work(self) -> None:
        name_os_thread("tslam-prepare")
        while True:
            while not self._slots.acquire(timeout=0.05):
                if self._stop.is_set():
                    return
            if self._stop.is_set():
                return
            try:
                frame = next(self._source)
            except StopIteration:
                self._results.put(("end", None, 0.0))
                return
            except BaseException as exc:  # handed to the consumer, which raises it
                self._results.put(("error", exc, 0.0))
                return
            t0 = time.perf_counter()
            try:
                self.system.prepare_ahead(frame)
            except Exception:  # noqa: BLE001 - track prepares the frame inline and raises it there
                logger.debug("prepare_ahead failed for frame %s; tracking prepares it", frame.index, exc_info=True)
            self._results.put(("frame", frame, time.perf_counter() - t0))


class AheadResults:
    """What a system's ``prepare_ahead`` left for its ``track``, by frame.

    The ahead thread puts a frame's result with the stage times it took (:meth:`put`);
    ``track`` takes it (:meth:`take`: the result of that very frame object only) and adds the
    stage times to its own. Each frame's entry is written once, by one thread, and taken once,
    by the other.
    """

    def __init__(self) -> None:
        self._items: dict[int, tuple[Frame, Any, dict[str, float]]] = {}

    def put(self, frame: Frame, value: Any, stage_ms: dict[str, float]) -> None:
        self._items[frame.index] = (frame, value, stage_ms)

    def take(self, frame: Frame, stage_ms: dict[str, float]) -> tuple[bool, Any]:
        """``(True, value)`` where ``frame`` was prepared ahead (its stage times are added to
        ``stage_ms``), else ``(False, None)``: ``track`` prepares it inline."""
        item = self._items.pop(frame.index, None)
        if item is None or item[0] is not frame:
            return False, None
        for stage, ms in item[2].items():
            stage_ms[stage] = stage_ms.get(stage, 0.0) + ms
        return True, item[1]

    def clear(self) -> None:
        """Drop what was prepared and never tracked (a stop before the end)."""
        self._items.clear()


def add_stage_ms(stage_ms: dict[str, float], stage: str, t0: float) -> float:
    """Add the milliseconds since ``t0`` (``time.perf_counter``) to ``stage_ms[stage]``; return now."""
    t1 = time.perf_counter()
    stage_ms[stage] = stage_ms.get(stage, 0.0) + 1000.0 * (t1 - t0)
    return t1


def empty_output(dtype: torch.dtype = torch.float64) -> SystemOutput:
    """An output with no frames (a system that was stopped before its first frame)."""
    return SystemOutput(
        frame_indices=torch.zeros(0, dtype=torch.int64),
        timestamps=torch.zeros(0, dtype=torch.float64),
        T_wc=torch.zeros(0, 4, 4, dtype=dtype),
        keyframe_indices=torch.zeros(0, dtype=torch.int64),
        keyframe_T_wc=torch.zeros(0, 4, 4, dtype=dtype),
    )


def resample_poses(t_from: Tensor, T_from: Tensor, t_to: Tensor, max_gap: float) -> Tensor:
    """Re-sample poses taken at instants ``t_from`` at the instants ``t_to`` (one per pose).

    Both systems track each frame at its depth image's instant, while the trajectory is reported
    at the frame (colour) timestamps; on TUM fr1 the two alternate ~15 ms before and after each
    other, which at 0.4 m/s is ±6 mm. Poses are interpolated (linear in translation, SLERP in
    rotation) between neighbouring instants of ``t_from``; poses outside their span, across a
    gap longer than ``max_gap``, or of a non-increasing ``t_from`` are kept as they are.

    Args:
        t_from: (N,) float64 instants of ``T_from``, seconds.
        T_from: (N, 4, 4) float64 poses.
        t_to: (N,) float64 instants to report them at.
        max_gap: largest gap of ``t_from`` interpolated across, seconds.

    Returns:
        (N, 4, 4) poses at ``t_to``.
    """
    from ..data.trajectory import Trajectory

    if len(t_from) < 2 or torch.equal(t_from, t_to) or not bool((t_from[1:] > t_from[:-1]).all()):
        return T_from
    T, ok = Trajectory(t_from, T_from).interpolate(t_to, max_gap)
    return torch.where(ok[:, None, None], T, T_from)


@dataclass(frozen=True)
class StepReport:
    """What a lockstep ``track_frames`` step did for each system (``nislam`` and ``gcslam``).

    Attributes:
        errors: per system, the exception one of its phases raised (its state is then undefined
            and it should be dropped), or None.
        compute_s: per system, seconds of compute attributed to it: its own phases plus an equal
            share of every batched call it took part in.
    """

    errors: list[Exception | None]
    compute_s: list[float]


def frame_poses(T_wk: Tensor, frame_kf: list[int], frame_T_kf: list[Tensor]) -> Tensor:
    """Pose every frame from its keyframe: ``T_wc = T_wk[kf] @ T_kf_frame``, batched.

    Args:
        T_wk: (K, 4, 4) float64 keyframe poses.
        frame_kf: N keyframe indices, one per frame.
        frame_T_kf: N (4, 4) poses of the frames relative to their keyframes.

    Returns:
        (N, 4, 4) float64 camera-to-world poses (on ``T_wk``'s device).
    """
    kf_of = torch.tensor(frame_kf, dtype=torch.int64, device=T_wk.device)
    return T_wk[kf_of] @ torch.stack(frame_T_kf).to(T_wk)
