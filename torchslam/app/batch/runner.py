"""Run one system on many sequences: the library behind ``torchslam batch``.

The sources are expanded into an ordered list of sequences with unique names (``sources``);
each sequence gets the run folder ``torchslam run`` writes, ``<out>/<name>/``, and the batch
gets one summary (``summary.md``, ``summary.csv``, ``summary.json``) with a row per sequence
(``summary``).

Execution. The sequences are cut into groups of ``batch_size`` and each group goes to a group
runner ``(system, system_cfg, sequences, device, monitors, max_frames) -> [RunResult |
BaseException]``. The default, :func:`run_group`, runs them one after another. For a system
whose registry spec declares ``lockstep`` and ``batch_size > 1``, the lockstep runner
``torchslam.systems.lockstep.run_lockstep`` is used (the group advances one frame of every
sequence per step: NI-SLAM back-projects and tracks the group's frames in batched calls while
keyframes, fusion and loops stay per sequence; GC-SLAM solves the group's pose graphs in one
FastGO call); ``summary.json`` records which engine ran.

Resuming (``resume``). A sequence whose folder already holds a complete run of the same request
is not run again; its row is read from its ``metrics.json`` and marked ``resumed``. A folder
holding an incomplete run (interrupted, failed, unreadable) is redone. A folder holding a
complete run of another request (system, data, config or ``max_frames``) is never replaced
silently: the batch is refused, naming those folders, unless ``overwrite`` is set. A redone
folder's old files are removed only when its new run is written, so an interruption never
leaves a folder emptier than it was.

Locking. The batch holds an exclusive lock on ``<out>/.torchslam-batch.lock`` (the file holds
the pid); a second batch on the same folder fails at once naming the first one's pid. Under
torchrun rank 0 takes the lock for the whole process group (``distributed``).

Failures. A source that cannot be opened, or a sequence whose run raises, becomes a ``failed``
row with a one-line message (naming the file for data errors) and the traceback in
``<name>/error.txt``; the other sequences go on. Ctrl-C stops the batch after keeping what was
computed (the interrupted sequence's folder is written with ``"interrupted": true``, so a rerun
redoes it) and the summary of what exists is written.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...data.frame import Sequence
from ...data.synthetic import generate_sequence
from ...data.trajectory import write_tum_trajectory
from ...errors import ConfigError, TorchSlamError
from ...systems.base import RunResult, check_max_frames, run_sequence
from ...systems.lockstep import run_lockstep
from ...systems.monitor import Monitor, TensorBoardMonitor
from ...systems.registry import get_system
from ...allocator import setup_allocator
from ...threads import setup_threads
from ..outputs import write_run
from ..progress import log_hparams
from ..run import DataConfig, load_sequence, resolve_config
from ..runfolder import BatchLock
from .distributed import Dist, gather_rows, init_distributed, lock_batch_folder, shard, sigterm_as_interrupt
from .resume import clear_files, completed_run, refuse_replacing_other_requests, run_files, sequence_config
from .sources import BatchSource, expand_sources
from .summary import summary_row, summary_totals, write_summary

__all__ = ["BatchOptions", "BatchResult", "GroupRunner", "run_batch", "run_group", "select_engine"]

logger = logging.getLogger(__name__)

# run_group's signature: (system, system_cfg, sequences, device, monitors, max_frames) -> results.
GroupRunner = Callable[[str, Any, list, str, list, int | None], list]

GROUNDTRUTH_FILE = "groundtruth.txt"
ERROR_FILE = "error.txt"


def run_group(
    system: str,
    system_cfg: Any,
    sequences: list[Sequence],
    device: str,
    monitors: list[Monitor],
    max_frames: int | None,
) -> list[RunResult | BaseException]:
    """Run a group of sequences one after another (the default engine).

    Args:
        system: the system's registry name.
        system_cfg: its config.
        sequences: the group's sequences.
        device: where the system's tensors live.
        monitors: one monitor per sequence.
        max_frames: stop each sequence after this many frames.

    Returns:
        Per sequence, its ``RunResult`` or the exception it raised. After a sequence was
        interrupted (Ctrl-C) the remaining ones are not run and hold a ``KeyboardInterrupt``.
    """
    spec = get_system(system)
    out: list[RunResult | BaseException] = []
    for seq, monitor in zip(sequences, monitors):
        if out and isinstance(out[-1], RunResult) and out[-1].interrupted:
            out.append(KeyboardInterrupt())
            continue
        try:
            out.append(run_sequence(spec.build(system_cfg, device=device, monitor=monitor), seq, max_frames=max_frames))
        except Exception as exc:  # reported in the summary; the other sequences go on
            logger.debug("%s failed", seq.name, exc_info=True)
            out.append(exc)
    return out


def select_engine(system: str, batch_size: int) -> tuple[str, GroupRunner]:
    """Choose how groups run: ``("lockstep", ...)`` for a system whose spec declares ``lockstep``
    and B > 1, else ``("sequential", run_group)``.

    Returns:
        (engine name, group runner with :func:`run_group`'s signature).
    """
    if batch_size > 1 and get_system(system).lockstep:

        def run_lockstep_group(system, system_cfg, sequences, device, monitors, max_frames):
            return run_lockstep(system_cfg, sequences, device, monitors, max_frames)

        return "lockstep", run_lockstep_group
    return "sequential", run_group


def _write_error(folder: Path, exc: BaseException) -> str:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / ERROR_FILE).write_text("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
    except OSError as write_exc:  # e.g. the disk is full: the row still says what went wrong
        logger.error("%s: cannot write %s (%s)", folder, ERROR_FILE, write_exc.strerror or write_exc)
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    return msg if isinstance(exc, TorchSlamError) else f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _finish_sequence(
    folder: Path,
    system: str,
    source: BatchSource,
    sequence: Sequence,
    result: RunResult,
    config: dict[str, Any],
    device: str,
    max_frames: int | None,
    monitor: Monitor,
    process: dict[str, Any],
) -> dict[str, Any]:
    """Write the run folder of one finished sequence (ground truth first, metrics.json last)."""
    extra: dict[str, Any] = {"device": device, "data": source.spec, "max_frames": max_frames, **process}
    # The sequence's own ground-truth file where it has one, so that evo run on the folder's two
    # files reproduces the headline ATE; a synthetic sequence's exact poses at its frames otherwise.
    groundtruth = sequence.groundtruth_raw or sequence.groundtruth
    if groundtruth is not None and len(groundtruth):
        folder.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(folder / GROUNDTRUTH_FILE, groundtruth, header=f"ground truth of {sequence.name} (camera-to-world)")
        extra["groundtruth_file"] = GROUNDTRUTH_FILE
    metrics = write_run(folder, system, result, sequence, config=config, extra=extra)
    log_hparams(monitor, config, metrics)
    return metrics


@dataclass(frozen=True)
class BatchOptions:
    """Everything about a batch that is not the system's own config.

    Attributes:
        system: the system's registry name.
        sources: folders, globs, ``synthetic`` or ``synthetic:K``.
        out: the batch folder.
        batch_size: sequences per group (the lockstep batch B).
        device: "cpu" or "cuda" (under torchrun with NCCL, each rank its ``LOCAL_RANK`` GPU).
        tensorboard: write TensorBoard events into each run folder.
        max_frames: stop each sequence after this many frames.
        overwrite: redo folders that hold a complete run of another request (else refuse).
        threads: intra-op threads for the process; None takes ``TORCHSLAM_THREADS`` or else the
            default of :mod:`torchslam.threads`. Each run folder and the summary record it.
    """

    system: str
    sources: tuple[str, ...]
    out: Path
    batch_size: int = 1
    device: str = "cpu"
    tensorboard: bool = True
    max_frames: int | None = None
    overwrite: bool = False
    threads: int | None = None


@dataclass
class BatchResult:
    """What a batch did.

    Attributes:
        rows: one summary row per sequence, in batch order (all ranks' rows when gathered).
        totals: :func:`summary_totals` of the rows.
        engine: "sequential" or "lockstep".
        interrupted: Ctrl-C stopped the batch.
        rank, world_size: this process's place in the process group (0 and 1 when alone).
        summary_files: the summary files this process wrote (rank 0 only).
    """

    rows: list[dict[str, Any]]
    totals: dict[str, Any]
    engine: str
    interrupted: bool
    rank: int = 0
    world_size: int = 1
    summary_files: list[Path] = field(default_factory=list)

    @property
    def failed(self) -> int:
        """Number of failed sequences."""
        return self.totals["failed"]


def _check_options(options: BatchOptions) -> None:
    if isinstance(options.batch_size, bool) or not isinstance(options.batch_size, int) or options.batch_size < 1:
        raise ConfigError(f"--batch-size: expected an integer >= 1, got {options.batch_size!r}")
    if options.device not in ("cpu", "cuda"):
        raise ConfigError(f"--device: expected 'cpu' or 'cuda', got {options.device!r}")
    check_max_frames(options.max_frames)
    if options.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise ConfigError("--device cuda: no CUDA device is available to this PyTorch build")
    out = Path(options.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a folder")


def run_batch(
    options: BatchOptions,
    config_path: str | os.PathLike | None = None,
    overrides: Iterable[str] = (),
    on_row: Callable[[dict[str, Any], int, int], None] | None = None,
    group_runner: GroupRunner | None = None,
) -> BatchResult:
    """Run ``options.system`` on every source and write the run folders and the summary.

    Args:
        options: system, sources, batch folder, batch size, device.
        config_path: YAML file overriding the system's defaults (as ``torchslam run``).
        overrides: ``key=value`` overrides (``data.synthetic.frames=50`` sets the generated
            sequences' base length).
        on_row: called with each finished row, the count done and the count this process has.
        group_runner: run groups with this instead of the engine :func:`select_engine` picks.

    Returns:
        The rows, totals, engine and whether the batch was interrupted.

    Raises:
        ConfigError: bad options, config, sources or distributed environment (before anything
            runs). Errors of single sequences do not raise: they are failed rows.
        OutputFolderError: another batch holds the folder's lock, or (without ``overwrite``)
            some run folders hold a complete run of another request (before anything runs).
    """
    _check_options(options)
    process = {**setup_threads(options.threads, flag_name="--threads").to_dict(), **setup_allocator().to_dict()}
    spec = get_system(options.system)
    system_cfg, data_cfg, resolved = resolve_config(options.system, config_path, overrides)
    sources = expand_sources(options.sources, data_cfg)
    engine, runner = select_engine(options.system, options.batch_size)
    if group_runner is not None:
        engine, runner = getattr(group_runner, "__name__", "custom"), group_runner
    dist = init_distributed(options.device)
    lock: BatchLock | None = None
    try:
        plan = _Plan(
            options=options,
            system=spec.name,
            system_cfg=system_cfg,
            data_cfg=data_cfg,
            configs={s.index: sequence_config(resolved, s, options.device) for s in sources},
            engine=engine,
            runner=runner,
            out=Path(options.out),
            device=f"cuda:{dist.local_rank}" if options.device == "cuda" and dist.active else options.device,
            process=process,
        )
        lock = lock_batch_folder(plan.out, dist)
        if not options.overwrite:
            refuse_replacing_other_requests(plan.out, plan.system, sources, plan.configs, options.max_frames)
        return _run_shard(plan, sources, dist, on_row)
    finally:
        if lock is not None:
            lock.release()
        if dist.initialised_here:
            import torch.distributed as tdist

            tdist.destroy_process_group()


@dataclass(frozen=True)
class _Plan:
    """The resolved batch, shared by the steps below."""

    options: BatchOptions
    system: str
    system_cfg: Any
    data_cfg: DataConfig
    configs: dict[int, dict[str, Any]]  # per sequence index: the config its run folder records
    engine: str
    runner: GroupRunner
    out: Path
    device: str  # where tensors live in this process
    process: dict[str, Any]  # the thread and C heap settings applied to this process at the start (their records)

    def completed(self, src: BatchSource) -> dict[str, Any] | None:
        if src.error is not None:
            return None
        return completed_run(self.out / src.name, self.system, src.spec, self.configs[src.index], self.options.max_frames)



def _run_shard(plan: _Plan, sources: list[BatchSource], dist: Dist, on_row) -> BatchResult:
    mine = shard(sources, dist)
    rows: dict[int, dict[str, Any]] = {}
    interrupted = False
    t0 = time.perf_counter()

    def emit(src: BatchSource, row: dict[str, Any]) -> None:
        rows[src.index] = row
        logger.info("%s: %s %s", src.name, row["status"], row["message"])
        if on_row is not None:
            on_row(row, len(rows), len(mine))

    plan.out.mkdir(parents=True, exist_ok=True)
    with sigterm_as_interrupt(dist.initialised_here):
        try:
            pending = []
            for src in mine:
                done = plan.completed(src)
                if done is not None:
                    emit(src, summary_row(src, "resumed", done))
                else:
                    pending.append(src)
            size = plan.options.batch_size
            for g in range(0, len(pending), size):
                if _run_one_group(plan, pending[g : g + size], emit):
                    interrupted = True
                    break
        except KeyboardInterrupt:
            interrupted = True
        if interrupted:
            logger.warning("batch interrupted; writing the summary of what was computed")
    wall = time.perf_counter() - t0
    for src in mine:
        if src.index not in rows:
            rows[src.index] = summary_row(src, "not run", message="the batch was interrupted before it")
    all_rows, walls, interrupted = gather_rows(dist, sources, rows, wall, interrupted, plan.completed)
    ordered = [all_rows[s.index] for s in sources]
    totals = summary_totals(ordered, max(walls))
    result = BatchResult(ordered, totals, plan.engine, interrupted, dist.rank, dist.world_size)
    if dist.rank == 0:
        o = plan.options
        header = {
            "system": plan.system,
            "engine": plan.engine,
            "batch_size": o.batch_size,
            "device": o.device,
            "world_size": dist.world_size,
            "rank_wall_s": walls,
            "sources": list(o.sources),
            "max_frames": o.max_frames,
            "interrupted": interrupted,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        result.summary_files = write_summary(plan.out, header, ordered, totals, plan.process)
    return result


def _run_one_group(plan: _Plan, group: list[BatchSource], emit: Callable[[BatchSource, dict[str, Any]], None]) -> bool:
    """Open, run and write one group; return whether it was interrupted."""
    o = plan.options
    loaded: list[tuple[BatchSource, Sequence]] = []
    # The earlier run's files go only when this sequence's new results (or error) are written:
    # a sequence that an interruption keeps from running keeps its folder as it was.
    stale: dict[str, list[Path]] = {}
    for src in group:
        folder = plan.out / src.name
        stale[src.name] = run_files(folder)
        try:
            if src.error is not None:
                raise ConfigError(src.error)
            seq = generate_sequence(src.synthetic) if src.synthetic is not None else load_sequence(src.spec, plan.data_cfg, plan.device)
        except Exception as exc:  # noqa: BLE001 -- any error of one source is that source's failed row
            clear_files(stale[src.name])
            emit(src, summary_row(src, "failed", message=_write_error(folder, exc)))
            continue
        loaded.append((src, seq))
    if not loaded:
        return False
    monitors = [TensorBoardMonitor(plan.out / s.name) if o.tensorboard else Monitor() for s, _ in loaded]
    interrupted = False
    try:
        results = plan.runner(plan.system, plan.system_cfg, [q for _, q in loaded], plan.device, monitors, o.max_frames)
        if len(results) != len(loaded):
            raise RuntimeError(f"{plan.engine} group runner returned {len(results)} results for {len(loaded)} sequences")
        for (src, seq), result, monitor in zip(loaded, results, monitors):
            folder = plan.out / src.name
            if isinstance(result, KeyboardInterrupt):  # not run: the group was stopped before it
                interrupted = True
                continue
            clear_files(stale[src.name])
            if isinstance(result, BaseException):
                emit(src, summary_row(src, "failed", message=_write_error(folder, result)))
                continue
            try:
                metrics = _finish_sequence(
                    folder, plan.system, src, seq, result, plan.configs[src.index], o.device, o.max_frames, monitor, plan.process
                )
            except Exception as exc:  # noqa: BLE001 -- e.g. a full disk: this sequence fails, not the batch
                emit(src, summary_row(src, "failed", message=_write_error(folder, exc)))
                continue
            if result.interrupted:
                interrupted = True
                emit(src, summary_row(src, "interrupted", metrics, "stopped by Ctrl-C; a rerun redoes it"))
            else:
                emit(src, summary_row(src, "ok", metrics))
    finally:
        for m in monitors:
            m.close()
    return interrupted


