"""The summary of a batch: one row per sequence read from its metrics, the totals, the Markdown
table, and the three summary files (``summary.json``, ``summary.csv``, ``summary.md``)."""

from __future__ import annotations

import csv
import io
import math
import os
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ...environment import environment_info
from ...strictjson import dumps as strict_dumps
from .sources import BatchSource

__all__ = [
    "STATUSES", "SUMMARY_COLUMNS", "TIMING_COLUMNS", "TOTAL_TIMING_KEYS", "as_count", "format_table", "loop_count", "summary_row",
    "summary_totals", "write_summary",
]

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


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def as_count(v: Any) -> int | None:
    """``v`` as a count: an integer, an integral float, or the length of a list; else None."""
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
    return as_count(v)


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
        "frames": as_count(m.get("frames")),
        "processed_frames": as_count(_first(m, ("processed_frames", "frames_processed"))),
        "tracked_frames": as_count(m.get("tracked_frames")),
        "keyframes": as_count(m.get("keyframes")),
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


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_summary(
    out: Path, header: dict[str, Any], rows: list[dict[str, Any]], totals: dict[str, Any], process: dict[str, Any]
) -> list[Path]:
    """Write ``summary.json``, ``summary.csv`` (one line per sequence) and ``summary.md``.

    ``process``: the records of the process's thread and C heap settings, added to ``environment``.
    """
    doc = {**header, "totals": totals, "rows": rows, "environment": {**environment_info(), **process}}
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
