"""Run one system on many sequences: the library behind ``torchslam batch``.

The sources are expanded into an ordered list of sequences with unique names; each sequence
gets the run folder ``torchslam run`` writes, ``<out>/<name>/``, and the batch gets one summary
(``summary.md``, ``summary.csv``, ``summary.json``) with a row per sequence.

Execution. The sequences are cut into groups of ``batch_size`` and each group goes to a group
runner ``(system, system_cfg, sequences, device, monitors, max_frames) -> [RunResult |
BaseException]``. The default, :func:`run_group`, runs them one after another. For NI-SLAM and
GC-SLAM with ``batch_size > 1`` the lockstep runner ``torchslam.systems.lockstep.run_lockstep`` is
used (the group advances in lockstep, NI-SLAM as one ``(B, ...)`` tensor); ``summary.json``
records which engine ran.

Resuming. A sequence whose folder already holds a complete run of the same request (see
:func:`completed_run`) is not run again; its row is read from its ``metrics.json`` and marked
``resumed``. A folder holding an incomplete run (interrupted, failed, unreadable) is redone. A
folder holding a complete run of another request (system, data, config or ``max_frames``) is
never replaced silently: the batch is refused, naming those folders, unless ``overwrite`` is set.
A redone folder's old files are removed only when its new run is written, so an interruption
never leaves a folder emptier than it was.

Locking. The batch holds an exclusive lock on ``<out>/.torchslam-batch.lock`` (the file holds
the pid); a second batch on the same folder fails at once naming the first one's pid. Under
torchrun rank 0 takes the lock for the whole process group.

Failures. A source that cannot be opened, or a sequence whose run raises, becomes a ``failed``
row with a one-line message (naming the file for data errors) and the traceback in
``<name>/error.txt``; the other sequences go on. Ctrl-C stops the batch after keeping what was
computed (the interrupted sequence's folder is written with ``"interrupted": true``, so a rerun
redoes it) and the summary of what exists is written.

Scale-out. Under ``torchrun`` (``RANK``, ``WORLD_SIZE`` and ``MASTER_ADDR`` in the environment)
the process group is initialised (gloo on the CPU, NCCL with ``device="cuda"``), sequence ``i``
goes to rank ``i % world_size``, each rank writes its own run folders, the rows are gathered with
``all_gather_object`` and rank 0 writes the one summary.
"""

from __future__ import annotations

import copy
import csv
import glob
import io
import json
import logging
import math
import os
import re
import signal
import statistics
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import timedelta
from pathlib import Path
from typing import Any

from ...config import config_to_dict, load_yaml
from ...data.frame import Sequence
from ...data.synthetic import SYNTHETIC_TRAJECTORIES, SyntheticConfig, generate_sequence
from ...data.trajectory import read_tum_trajectory, write_tum_trajectory
from ...environment import environment_info
from ...errors import ConfigError, TorchSlamError
from ...threads import ThreadSetting, setup_threads
from ...strictjson import dumps as strict_dumps
from ...systems.base import RunResult, check_max_frames, run_sequence
from ...systems.lockstep import run_lockstep
from ...systems.monitor import Monitor, TensorBoardMonitor
from ..outputs import write_run
from ..progress import log_hparams
from ...systems.registry import get_system
from ..run import SYNTHETIC, DataConfig, load_sequence, resolve_config
from ..runfolder import BatchLock, OutputFolderError, is_run_file

__all__ = [
    "STATUSES",
    "SUMMARY_COLUMNS",
    "TIMING_COLUMNS",
    "TOTAL_TIMING_KEYS",
    "BatchOptions",
    "BatchResult",
    "BatchSource",
    "GroupRunner",
    "completed_run",
    "expand_sources",
    "format_table",
    "loop_count",
    "run_batch",
    "run_group",
    "select_engine",
    "summary_row",
    "summary_totals",
]

logger = logging.getLogger(__name__)

# run_group's signature: (system, system_cfg, sequences, device, monitors, max_frames) -> results.
GroupRunner = Callable[[str, Any, list, str, list, int | None], list]

# Row keys, in the order of summary.csv's columns.
SUMMARY_COLUMNS = (
    "name",
    "status",
    "frames",
    "processed_frames",
    "tracked_frames",
    "keyframes",
    "loops",
    "ate_rmse_m",
    "fps_end_to_end",
    "fps_compute",
    "wall_s",
    "source",
    "message",
)
# Columns (and totals) that measure time: they differ from run to run.
TIMING_COLUMNS = ("fps_end_to_end", "fps_compute", "wall_s")
TOTAL_TIMING_KEYS = ("wall_s", "fps_aggregate")

STATUSES = ("ok", "resumed", "failed", "interrupted", "not run")

GROUNDTRUTH_FILE = "groundtruth.txt"
ERROR_FILE = "error.txt"
# Names in the batch folder that are not run folders.
_RESERVED_NAMES = frozenset({"summary.md", "summary.csv", "summary.json", "report.md", "report"})
_SYNTHETIC_SOURCE = re.compile(r"^synthetic(?::(.*))?$")
# Ranks wait for the slowest one at the final gather; a batch can take hours.
DIST_TIMEOUT = timedelta(hours=12)


# --------------------------------------------------------------------------------------------
# Sources


@dataclass(frozen=True)
class BatchSource:
    """One sequence of a batch, before it is opened.

    Attributes:
        index: position in the batch (rows and sharding follow it).
        name: unique, file-system-safe name; the run folder is ``<out>/<name>``.
        spec: what the run records as its data: an absolute folder path, or ``"synthetic"``.
        source: the command-line source it came from (``synthetic:4``, a glob, a folder).
        synthetic: the generator's settings for a synthetic sequence, else None.
        error: why the source yields no sequence (a glob that matches no folder), else None.
    """

    index: int
    name: str
    spec: str
    source: str
    synthetic: SyntheticConfig | None = None
    error: str | None = None


def _safe_name(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return s or "sequence"


def _synthetic_variant(base: SyntheticConfig, j: int) -> SyntheticConfig:
    """The ``j``-th generated sequence: seed ``base.seed + j``, trajectory kind and length cycled.

    Sequence 0 is ``base`` itself (what ``torchslam run --data synthetic`` runs); the kinds cycle
    through ``SYNTHETIC_TRAJECTORIES`` from ``base.trajectory`` and the lengths through
    ``base.frames`` minus 0, 1, 2, 3 eighths, so a batch mixes motions and lengths.
    """
    kinds = SYNTHETIC_TRAJECTORIES
    kind = kinds[(kinds.index(base.trajectory) + j) % len(kinds)]
    step = max(1, base.frames // 8)
    frames = max(min(base.frames, 2), base.frames - (j % 4) * step)
    return replace(base, seed=base.seed + j, trajectory=kind, frames=frames)


def expand_sources(sources: Iterable[str], data_cfg: DataConfig) -> list[BatchSource]:
    """Turn command-line sources into the batch's ordered list of sequences.

    ``synthetic`` is one generated sequence with ``data_cfg.synthetic``; ``synthetic:K`` is K of
    them with distinct seeds (see :func:`_synthetic_variant`; numbering continues across
    several ``synthetic:K`` sources). A pattern with ``*``, ``?`` or ``[`` expands to the folders
    it matches, sorted (a pattern matching none is kept as a source that fails). Anything else is
    a sequence folder; whether it is one is found out when it is opened. A folder listed twice
    is run once.

    Raises:
        ConfigError: no sources, or ``synthetic:K`` with K not an integer >= 1.
    """
    sources = list(sources)
    if not sources:
        raise ConfigError("SOURCES: expected at least one sequence folder, glob or synthetic:K")
    entries: list[tuple[str, str, SyntheticConfig | None, str | None]] = []  # (name, spec, synthetic, error)
    origins: list[str] = []
    seen: set[str] = set()
    n_synthetic = 0
    for src in sources:
        if not isinstance(src, str) or not src:
            raise ConfigError(f"SOURCES: expected non-empty strings, got {src!r}")
        m = _SYNTHETIC_SOURCE.match(src)
        if m:
            count = 1
            if m.group(1) is not None:
                try:
                    count = int(m.group(1))
                except ValueError:
                    count = 0
                if count < 1:
                    raise ConfigError(f"SOURCES: {src!r}: expected synthetic:K with K an integer >= 1")
            for _ in range(count):
                cfg = _synthetic_variant(data_cfg.synthetic, n_synthetic)
                n_synthetic += 1
                entries.append((f"synthetic-{cfg.trajectory}-seed{cfg.seed}", SYNTHETIC, cfg, None))
                origins.append(src)
            continue
        if glob.has_magic(src):
            folders = sorted(p for p in glob.glob(os.path.expanduser(src)) if os.path.isdir(p))
            if not folders:
                entries.append((Path(src).name, src, None, f"{src}: the pattern matches no folder"))
                origins.append(src)
            paths = folders
        else:
            paths = [os.path.expanduser(src)]
        for p in paths:
            spec = str(Path(p).resolve())
            if spec in seen:
                logger.warning("%s is listed more than once; running it once", spec)
                continue
            seen.add(spec)
            entries.append((Path(spec).name, spec, None, None))
            origins.append(src)
    out: list[BatchSource] = []
    used: set[str] = set()
    for i, ((name, spec, syn, err), origin) in enumerate(zip(entries, origins)):
        base = _safe_name(name)
        unique, k = base, 2
        while unique in used or unique in _RESERVED_NAMES:
            unique, k = f"{base}-{k}", k + 1
        used.add(unique)
        out.append(BatchSource(index=i, name=unique, spec=spec, source=origin, synthetic=syn, error=err))
    return out


# --------------------------------------------------------------------------------------------
# Rows


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _count(v: Any) -> int | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, int):
        return v
    if isinstance(v, float) and math.isfinite(v) and v == int(v):
        return int(v)
    if isinstance(v, (list, tuple)):
        return len(v)
    return None


def _first(m: Mapping[str, Any], keys: Iterable[str]) -> Any:
    for k in keys:
        if m.get(k) is not None:
            return m[k]
    return None


def loop_count(metrics: Mapping[str, Any]) -> int | None:
    """Accepted loop closures of a run, read tolerantly from its metrics.

    Systems record loops differently: NI-SLAM writes ``loops: {candidates, verified, accepted,
    ...}``; a count, a list of loops or keys such as ``loop_closures`` are read too.

    Returns:
        The number of loops, or None where the metrics do not say.
    """
    v = _first(metrics, ("loops", "loop_closures", "loops_accepted", "num_loops", "loop_count"))
    if isinstance(v, Mapping):
        v = _first(v, ("accepted", "closed", "closures", "count", "verified"))
    return _count(v)


def summary_row(source: BatchSource, status: str, metrics: Mapping[str, Any] | None = None, message: str = "") -> dict[str, Any]:
    """One summary row: the sequence's status and its figures read from its metrics.

    Args:
        source: the sequence.
        status: one of ``ok``, ``resumed``, ``failed``, ``interrupted``, ``not run``. An ``ok``
            or ``resumed`` run whose metrics hold an ``ate_error`` (ground truth present, no ATE
            computable) becomes ``failed`` with the message ``evaluation failed: ...``.
        metrics: the run's ``metrics.json`` content, or None.
        message: why it failed, or a note.
    """
    m = metrics or {}
    if m.get("ate_error") and status in ("ok", "resumed"):
        # The run is complete but has no accuracy figure although there is ground truth
        # (e.g. non-finite values): that is a failure, not a plain "ok".
        status = "failed"
        message = f"evaluation failed: {m['ate_error']}" + (f"; {message}" if message else "")
    return {
        "name": source.name,
        "status": status,
        "frames": _count(m.get("frames")),
        "processed_frames": _count(_first(m, ("processed_frames", "frames_processed"))),
        "tracked_frames": _count(m.get("tracked_frames")),
        "keyframes": _count(m.get("keyframes")),
        "loops": loop_count(m),
        "ate_rmse_m": _number(_first(m, ("ate_rmse_m", "ate_rmse"))),
        "fps_end_to_end": _number(_first(m, ("fps_end_to_end", "fps"))),
        "fps_compute": _number(m.get("fps_compute")),
        "wall_s": _number(m.get("wall_s")),
        "source": source.source,
        "message": message,
    }


def summary_totals(rows: list[Mapping[str, Any]], wall_s: float) -> dict[str, Any]:
    """Totals of a batch: counts per status, summed frames/keyframes/loops, mean ATE, throughput.

    ``fps_aggregate`` is the frames processed by this invocation (not resumed ones) over the
    batch's wall time ``wall_s``: frames per second summed over sequences.
    """

    def total(key: str, statuses: tuple[str, ...]) -> int:
        return sum(r[key] for r in rows if r["status"] in statuses and r[key] is not None)

    done = ("ok", "resumed", "interrupted")
    ates = [r["ate_rmse_m"] for r in rows if r["status"] in ("ok", "resumed") and r["ate_rmse_m"] is not None]
    new_frames = total("processed_frames", ("ok", "interrupted"))
    out: dict[str, Any] = {"sequences": len(rows)}
    for s in STATUSES:
        out[s.replace(" ", "_")] = sum(r["status"] == s for r in rows)
    out.update(
        {
            "processed_frames": total("processed_frames", done),
            "tracked_frames": total("tracked_frames", done),
            "keyframes": total("keyframes", done),
            "loops": total("loops", done),
            "ate_rmse_m_mean": sum(ates) / len(ates) if ates else None,
            "ate_rmse_m_median": statistics.median(ates) if ates else None,
            "new_frames": new_frames,
            "wall_s": wall_s,
            "fps_aggregate": new_frames / wall_s if wall_s > 0 and new_frames else None,
        }
    )
    return out


def _cell(v: Any, fmt: str = "{}") -> str:
    return "–" if v is None else fmt.format(v)


def format_table(rows: list[Mapping[str, Any]], totals: Mapping[str, Any] | None = None) -> str:
    """Render rows (and totals) as a Markdown table: status, frames, keyframes, loops, ATE, frames/s."""
    lines = [
        "| sequence | status | frames | tracked | keyframes | loops | ATE RMSE (cm) | frames/s | note |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        frames = "–" if r["processed_frames"] is None else f"{r['processed_frames']}/{_cell(r['frames'])}"
        ate_cm = None if r["ate_rmse_m"] is None else r["ate_rmse_m"] * 100
        note = str(r.get("message") or "").replace("|", "\\|").replace("\n", " ")
        lines.append(
            f"| {r['name']} | {r['status']} | {frames} | {_cell(r['tracked_frames'])} | {_cell(r['keyframes'])} | "
            f"{_cell(r['loops'])} | {_cell(ate_cm, '{:.2f}')} | {_cell(r['fps_end_to_end'], '{:.1f}')} | {note} |"
        )
    if totals is not None:
        counts = ", ".join(f"{totals[s.replace(' ', '_')]} {s}" for s in STATUSES if totals[s.replace(" ", "_")])
        mean_cm = None if totals["ate_rmse_m_mean"] is None else totals["ate_rmse_m_mean"] * 100
        lines.append(
            f"| **total** ({totals['sequences']}) | {counts} | {totals['processed_frames']} | {totals['tracked_frames']} | "
            f"{totals['keyframes']} | {totals['loops']} | {_cell(mean_cm, 'mean {:.2f}')} | "
            f"{_cell(totals['fps_aggregate'], '{:.1f}')} | frames/s: aggregate over {totals['wall_s']:.1f} s |"
        )
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Group runners


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
            logger.debug("%s failed", getattr(seq, "name", "?"), exc_info=True)
            out.append(exc)
    return out


def select_engine(system: str, batch_size: int) -> tuple[str, GroupRunner]:
    """Choose how groups run: ``("lockstep", ...)`` for NI-SLAM and GC-SLAM with B > 1, else sequential.

    NI-SLAM in lockstep batches its per-frame tensor work; GC-SLAM in lockstep solves the pose
    graphs of the group's sequences in one FastGO call per step.

    Returns:
        (engine name, group runner with :func:`run_group`'s signature).
    """
    if system in ("nislam", "gcslam") and batch_size > 1:

        def run_lockstep_group(system, system_cfg, sequences, device, monitors, max_frames):
            return run_lockstep(system_cfg, sequences, device, monitors, max_frames)

        return "lockstep", run_lockstep_group
    return "sequential", run_group


# --------------------------------------------------------------------------------------------
# Run folders


def _sequence_config(resolved: Mapping[str, Any], source: BatchSource, device: str) -> dict[str, Any]:
    cfg = copy.deepcopy(dict(resolved))
    if source.synthetic is not None:
        cfg["data"]["synthetic"] = config_to_dict(source.synthetic)
    cfg["device"] = device
    return cfg


def _without_device(cfg: Any) -> Any:
    return {k: v for k, v in cfg.items() if k != "device"} if isinstance(cfg, dict) else cfg


def completed_run(
    folder: str | os.PathLike,
    system: str,
    spec: str | None = None,
    config: Mapping[str, Any] | None = None,
    max_frames: int | None = None,
) -> dict[str, Any] | None:
    """Return the metrics of ``folder`` if it holds a complete run of this request, else None.

    Complete means: ``metrics.json`` parses to a mapping of ``system`` with ``processed_frames``
    and without ``"interrupted": true``, and ``trajectory.txt`` parses with ``posed_frames``
    (older runs: ``tracked_frames``) poses. The same request means, where given: the same data
    ``spec``, the same resolved ``config`` (``config.yaml``; the device may differ) and the same
    ``max_frames``.
    """
    metrics, why, _ = _run_state(Path(folder), system, spec, config, max_frames)
    if why is not None:
        if Path(folder).is_dir():
            logger.info("%s: redoing (%s)", folder, why)
        return None
    return metrics


def _differing_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested mappings."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [prefix or "(the whole config)"] if a != b else []
    out: list[str] = []
    for k in sorted(set(a) | set(b), key=str):
        out += _differing_keys(a.get(k), b.get(k), f"{prefix}{k}.") if isinstance(a.get(k), dict) and isinstance(b.get(k), dict) else (
            [f"{prefix}{k}"] if a.get(k) != b.get(k) else []
        )
    return out


def _run_state(
    folder: Path, system: str, spec: str | None, config: Mapping[str, Any] | None, max_frames: int | None
) -> tuple[dict[str, Any] | None, str | None, bool]:
    """(metrics, why it is not a complete run of this request or None, whether it is a complete run at all)."""
    why = None
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError) as exc:
        return None, f"metrics.json unreadable ({exc.__class__.__name__})", False
    if not isinstance(metrics, dict):
        return None, "metrics.json is not a mapping", False
    if _count(metrics.get("processed_frames")) is None:
        return None, "metrics.json has no processed_frames", False
    if metrics.get("interrupted") is not False:
        return None, "the run was interrupted", False
    try:
        traj = read_tum_trajectory(folder / "trajectory.txt")
        # posed_frames = tracked + on a motion prior; runs written before it have only tracked_frames.
        key = "posed_frames" if metrics.get("posed_frames") is not None else "tracked_frames"
        if metrics.get(key) is not None and len(traj) != metrics[key]:
            why = f"trajectory.txt has {len(traj)} poses, metrics.json says {key} {metrics[key]}"
    except TorchSlamError as exc:
        why = f"trajectory.txt: {exc}"
    if why is not None:
        return None, why, False
    # A complete run: is it this request's?
    if metrics.get("system") != system:
        why = f"system {metrics.get('system')!r}, not {system!r}"
    elif spec is not None and metrics.get("data") != spec:
        why = f"data {metrics.get('data')!r}, not {spec!r}"
    elif metrics.get("max_frames") != max_frames:
        why = f"max_frames {metrics.get('max_frames')}, not {max_frames}"
    elif config is not None:
        try:
            saved = load_yaml((folder / "config.yaml").read_text(), str(folder / "config.yaml"))
        except (OSError, ConfigError) as exc:
            return None, f"config.yaml unreadable ({exc.__class__.__name__})", False
        if _without_device(saved) != _without_device(dict(config)):
            keys = _differing_keys(_without_device(saved), _without_device(dict(config)))
            why = f"the configuration differs: {', '.join(keys[:3])}{' ...' if len(keys) > 3 else ''}"
    return (None, why, True) if why is not None else (metrics, None, True)


def _run_files(folder: Path) -> list[Path]:
    """The files of an earlier run in ``folder`` (anything else there is left alone)."""
    if not folder.is_dir():
        return []
    return [p for p in folder.iterdir() if is_run_file(p.name) and p.is_file()]


def _clear(files: Iterable[Path]) -> None:
    for f in files:
        f.unlink(missing_ok=True)


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
    threads: ThreadSetting,
) -> dict[str, Any]:
    """Write the run folder of one finished sequence (ground truth first, metrics.json last)."""
    extra: dict[str, Any] = {"device": device, "data": source.spec, "max_frames": max_frames, **threads.to_dict()}
    # The sequence's own ground-truth file where it has one, so that evo run on the folder's two
    # files reproduces the headline ATE; a synthetic sequence's exact poses at its frames otherwise.
    groundtruth = getattr(sequence, "groundtruth_raw", None) or sequence.groundtruth
    if groundtruth is not None and len(groundtruth):
        folder.mkdir(parents=True, exist_ok=True)
        write_tum_trajectory(folder / GROUNDTRUTH_FILE, groundtruth, header=f"ground truth of {sequence.name} (camera-to-world)")
        extra["groundtruth_file"] = GROUNDTRUTH_FILE
    metrics = write_run(folder, system, result, sequence, config=config, extra=extra)
    log_hparams(monitor, config, metrics)
    return metrics


# --------------------------------------------------------------------------------------------
# Distributed


@dataclass(frozen=True)
class _Dist:
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


def _init_distributed(device: str) -> _Dist:
    """Join the torchrun process group where the environment names one; else run alone."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return _Dist(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")), False, True)
    if "RANK" not in os.environ or "WORLD_SIZE" not in os.environ:
        return _Dist()
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
    return _Dist(rank, world, local, True, True)


@contextmanager
def _sigterm_as_interrupt(enabled: bool) -> Iterator[None]:
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


# --------------------------------------------------------------------------------------------
# The batch


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
    threads = setup_threads(options.threads, flag_name="--threads")
    spec = get_system(options.system)
    system_cfg, data_cfg, resolved = resolve_config(options.system, config_path, overrides)
    sources = expand_sources(options.sources, data_cfg)
    engine, runner = select_engine(options.system, options.batch_size)
    if group_runner is not None:
        engine, runner = getattr(group_runner, "__name__", "custom"), group_runner
    dist = _init_distributed(options.device)
    lock: BatchLock | None = None
    try:
        plan = _Plan(
            options=options,
            system=spec.name,
            system_cfg=system_cfg,
            data_cfg=data_cfg,
            configs={s.index: _sequence_config(resolved, s, options.device) for s in sources},
            engine=engine,
            runner=runner,
            out=Path(options.out),
            device=f"cuda:{dist.local_rank}" if options.device == "cuda" and dist.active else options.device,
            threads=threads,
        )
        lock = _lock_batch_folder(plan.out, dist)
        if not options.overwrite:
            _refuse_replacing_other_requests(plan, sources)
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
    threads: ThreadSetting  # applied to this process at the start

    def completed(self, src: BatchSource) -> dict[str, Any] | None:
        if src.error is not None:
            return None
        return completed_run(self.out / src.name, self.system, src.spec, self.configs[src.index], self.options.max_frames)


def _lock_batch_folder(out: Path, dist: _Dist) -> BatchLock | None:
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


def _refuse_replacing_other_requests(plan: _Plan, sources: list[BatchSource]) -> None:
    """Raise OutputFolderError naming the run folders that hold a complete run of another request."""
    differing = []
    for src in sources:
        folder = plan.out / src.name
        if src.error is not None or not folder.is_dir():
            continue
        _, why, complete = _run_state(folder, plan.system, src.spec, plan.configs[src.index], plan.options.max_frames)
        if complete and why is not None:
            differing.append(f"{src.name} ({why})")
    if differing:
        raise OutputFolderError(
            f"--out {plan.out}: {len(differing)} run folder(s) hold a complete run of another request that this batch "
            f"would replace: {', '.join(differing)}; pass --overwrite to redo them, or choose another --out"
        )


def _run_shard(plan: _Plan, sources: list[BatchSource], dist: _Dist, on_row) -> BatchResult:
    mine = sources[dist.rank :: dist.world_size]
    rows: dict[int, dict[str, Any]] = {}
    interrupted = False
    t0 = time.perf_counter()

    def emit(src: BatchSource, row: dict[str, Any]) -> None:
        rows[src.index] = row
        logger.info("%s: %s %s", src.name, row["status"], row["message"])
        if on_row is not None:
            on_row(row, len(rows), len(mine))

    plan.out.mkdir(parents=True, exist_ok=True)
    with _sigterm_as_interrupt(dist.initialised_here):
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
    all_rows, walls, interrupted = _gather(plan, dist, sources, rows, wall, interrupted)
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
        result.summary_files = _write_summary(plan.out, header, ordered, totals, plan.threads)
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
        stale[src.name] = _run_files(folder)
        try:
            if src.error is not None:
                raise ConfigError(src.error)
            seq = generate_sequence(src.synthetic) if src.synthetic is not None else load_sequence(src.spec, plan.data_cfg)
        except Exception as exc:  # noqa: BLE001 -- any error of one source is that source's failed row
            _clear(stale[src.name])
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
            _clear(stale[src.name])
            if isinstance(result, BaseException):
                emit(src, summary_row(src, "failed", message=_write_error(folder, result)))
                continue
            try:
                metrics = _finish_sequence(
                    folder, plan.system, src, seq, result, plan.configs[src.index], o.device, o.max_frames, monitor, plan.threads
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


def _gather(plan: _Plan, dist: _Dist, sources: list[BatchSource], rows: dict[int, dict[str, Any]], wall: float, interrupted: bool):
    """Bring every rank's rows to every rank; after an interruption rank 0 reads the others' folders."""
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
        done = plan.completed(src)
        merged[src.index] = (
            summary_row(src, "ok", done, "read from its folder after the interruption")
            if done is not None
            else summary_row(src, "not run", message="another rank's sequence; not finished at the interruption")
        )
    return merged, [wall], True


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_summary(
    out: Path, header: dict[str, Any], rows: list[dict[str, Any]], totals: dict[str, Any], threads: ThreadSetting
) -> list[Path]:
    """Write ``summary.json``, ``summary.csv`` (one line per sequence) and ``summary.md``."""
    doc = {**header, "totals": totals, "rows": rows, "environment": {**environment_info(), **threads.to_dict()}}
    paths = [out / "summary.json", out / "summary.csv", out / "summary.md"]
    _write_atomic(paths[0], strict_dumps(doc) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: "" if r[k] is None else r[k] for k in SUMMARY_COLUMNS})
    _write_atomic(paths[1], buf.getvalue())
    title = f"# torchslam batch: {header['system']} on {len(rows)} sequences\n\n"
    info = (
        f"engine {header['engine']}, batch size {header['batch_size']}, device {header['device']}, "
        f"{header['world_size']} process(es), max frames {header['max_frames'] or 'all'}"
        f"{', **interrupted**' if header['interrupted'] else ''}; {header['created']}\n\n"
    )
    _write_atomic(paths[2], title + info + format_table(rows, totals))
    return paths
