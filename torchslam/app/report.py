"""Turn a batch folder into a Markdown report with plots: the library behind ``torchslam report``.

The report reads ``summary.json`` (or, for a folder of plain ``torchslam run`` folders, every
sub-folder holding a ``metrics.json`` of a known system; other sub-folders, such as a training
folder of ``scripts/train.py``, are skipped and counted) and writes ``report.md`` beside it, with its images in
``report/``: ATE RMSE per sequence, frames/s per sequence, and a top view of every sequence's
estimated trajectory, aligned onto the ground truth (rigidly, as the ATE is computed) where the
ground truth can be found. "Top" is the plane of the two world axes along which the ground truth
(else the estimate) moves most, since the datasets disagree on which axis is up; for a camera
carried around a room that is the floor plane.

Ground truth is looked for, in order, at the run folder's ``metrics.json`` key
``groundtruth_file`` (``torchslam batch`` writes ``groundtruth.txt`` into every run folder),
at ``groundtruth.txt`` in the sequence folder ``metrics.json`` names as its ``data``, and, for a
synthetic run, by evaluating the generator's analytic trajectory with the settings in the run's
``config.yaml``.

The plots are drawn by :mod:`torchslam.app.plots`.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..data.trajectory import Trajectory, read_tum_trajectory
from ..errors import DataFormatError, TorchSlamError
from .batch import BatchSource, format_table, summary_row, summary_totals
from .plots import bar_chart, trajectory_plot

__all__ = ["find_groundtruth", "load_batch", "write_report"]

logger = logging.getLogger(__name__)

ASSETS = "report"


def load_batch(batch_dir: str | os.PathLike) -> dict[str, Any]:
    """Read a batch folder's ``summary.json``, or build the same document from its run folders.

    Built from run folders, the document also lists under ``skipped`` the sub-folders that are
    not runs (no ``metrics.json`` of a known system), and a warning counts them.

    Raises:
        DataFormatError: ``batch_dir`` is not a folder, its ``summary.json`` is malformed, or it
            holds neither a summary nor any run folder.
    """
    root = Path(batch_dir)
    if not root.is_dir():
        raise DataFormatError(f"{root}: not a folder (expected a batch folder written by 'torchslam batch')")
    path = root / "summary.json"
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
        except ValueError as exc:
            raise DataFormatError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(doc, dict) or not isinstance(doc.get("rows"), list):
            raise DataFormatError(f"{path}: expected a mapping with a 'rows' list")
        for i, row in enumerate(doc["rows"]):
            if not isinstance(row, dict) or not isinstance(row.get("name"), str) or "status" not in row:
                raise DataFormatError(f"{path}: rows[{i}]: expected a mapping with 'name' and 'status'")
        return doc
    rows, systems, skipped = [], set(), []
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and p.name != ASSETS and not p.name.startswith(".")):
        metrics = _run_metrics(folder)
        if metrics is None:
            skipped.append(folder.name)
            continue
        systems.add(str(metrics.get("system")))
        status = "interrupted" if metrics.get("interrupted") else "ok"
        data = str(metrics.get("data", ""))
        src = BatchSource(index=len(rows), name=folder.name, spec=data, source=data)
        rows.append(summary_row(src, status, metrics))
    if not rows:
        why = f" ({len(skipped)} sub-folders are not runs: {_names(skipped)})" if skipped else ""
        raise DataFormatError(f"{root}: no summary.json and no run folders with metrics.json{why}")
    if skipped:
        logger.warning("%s: skipped %d folder(s) that are not runs: %s", root, len(skipped), _names(skipped))
    return {
        "system": ", ".join(sorted(systems)),
        "engine": None,
        "rows": rows,
        "totals": summary_totals(rows, sum(r["wall_s"] or 0.0 for r in rows)),
        "skipped": skipped,
    }


def _run_metrics(folder: Path) -> dict[str, Any] | None:
    """The ``metrics.json`` of a run folder, or None for a folder that is not a run.

    A run folder holds a ``metrics.json`` whose ``system`` is a known system; a training folder
    (``scripts/train.py``) or anything else is not one.

    Raises:
        DataFormatError: ``metrics.json`` is not valid JSON.
    """
    from ..systems.registry import KNOWN_SYSTEMS

    path = folder / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = json.loads(path.read_text())
    except ValueError as exc:
        raise DataFormatError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(metrics, dict) or metrics.get("system") not in KNOWN_SYSTEMS:
        return None
    return metrics


def _names(names: list[str], limit: int = 5) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def find_groundtruth(run_dir: str | os.PathLike, metrics: Mapping[str, Any]) -> Trajectory | None:
    """Return the ground truth of a run folder (see the module docstring), or None."""
    run_dir = Path(run_dir)
    candidates = []
    if isinstance(metrics.get("groundtruth_file"), str):
        candidates.append(run_dir / metrics["groundtruth_file"])  # an absolute path stays absolute
    data = metrics.get("data")
    if isinstance(data, str) and data and data != "synthetic":
        candidates.append(Path(data) / "groundtruth.txt")
    for path in candidates:
        if path.is_file():
            try:
                return read_tum_trajectory(path)
            except TorchSlamError as exc:
                logger.warning("%s: ground truth unreadable: %s", path, exc)
    if data == "synthetic":
        return _synthetic_groundtruth(run_dir)
    return None


def _synthetic_groundtruth(run_dir: Path) -> Trajectory | None:
    from ..config import config_from_dict, load_yaml
    from ..data.synthetic import SyntheticConfig, synthetic_trajectory
    from ..geometry import se3_from_Rt

    try:
        cfg_doc = load_yaml((run_dir / "config.yaml").read_text(), str(run_dir / "config.yaml"))
        cfg = config_from_dict(SyntheticConfig, cfg_doc["data"]["synthetic"])
    except (OSError, KeyError, TypeError, TorchSlamError) as exc:
        logger.warning("%s: cannot rebuild the synthetic ground truth (%s)", run_dir, exc)
        return None
    t = torch.arange(cfg.frames, dtype=torch.float64) / cfg.fps
    R, p = synthetic_trajectory(cfg)(t)
    return Trajectory(t, se3_from_Rt(R, p).detach())


def write_report(batch_dir: str | os.PathLike) -> Path:
    """Write ``report.md`` and its plots (``report/*.png``) for a batch folder.

    Args:
        batch_dir: a folder written by ``torchslam batch`` (or one holding run folders).

    Returns:
        The path of ``report.md``.

    Raises:
        DataFormatError: as :func:`load_batch`.
    """
    root = Path(batch_dir)
    doc = load_batch(root)
    rows = doc["rows"]
    assets = root / ASSETS
    assets.mkdir(exist_ok=True)
    totals = doc.get("totals")
    lines = [f"# torchslam batch report: {doc.get('system')} on {len(rows)} sequences", ""]
    details = [f"{k} {doc[k]}" for k in ("engine", "batch_size", "device", "world_size") if doc.get(k) is not None]
    if details:
        lines += [", ".join(details) + (" (interrupted)" if doc.get("interrupted") else ""), ""]
    lines += ["## Sequences", "", format_table(rows, totals if isinstance(totals, dict) and "fps_aggregate" in totals else None)]
    skipped = doc.get("skipped") or []
    if skipped:
        lines += [f"Skipped {len(skipped)} sub-folder(s) that are not runs (no metrics.json of a known system): "
                  f"{_names(skipped)}.", ""]

    with_ate = [(r["name"], r["ate_rmse_m"] * 100) for r in rows if r.get("ate_rmse_m") is not None]
    lines += ["## ATE RMSE per sequence", ""]
    if with_ate:
        bar_chart(assets / "ate.png", [n for n, _ in with_ate], [v for _, v in with_ate], "ATE RMSE (cm)", "ATE RMSE per sequence (SE(3)-aligned)")
        lines += [f"![ATE RMSE per sequence]({ASSETS}/ate.png)", ""]
    else:
        lines += ["No sequence has an ATE (no ground truth, or no sequence finished).", ""]
    with_fps = [(r["name"], r["fps_end_to_end"]) for r in rows if r.get("fps_end_to_end") is not None]
    lines += ["## Frames per second", ""]
    if with_fps:
        bar_chart(assets / "fps.png", [n for n, _ in with_fps], [v for _, v in with_fps], "frames/s (end to end)", "Throughput per sequence")
        lines += [f"![frames per second]({ASSETS}/fps.png)", ""]
    else:
        lines += ["No sequence has a frame rate.", ""]

    lines += ["## Trajectories (top view: the plane of largest motion)", ""]
    for r in rows:
        folder = root / r["name"]
        try:
            metrics = json.loads((folder / "metrics.json").read_text())
            estimate = read_tum_trajectory(folder / "trajectory.txt")
        except (OSError, ValueError, TorchSlamError):
            continue
        if len(estimate) == 0:
            continue
        png = f"traj-{r['name']}.png"
        caption = trajectory_plot(assets / png, r["name"], estimate, find_groundtruth(folder, metrics))
        lines += [f"### {r['name']}", "", f"![{r['name']}]({ASSETS}/{png})", "", caption + ".", ""]

    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        lines += ["## Failures", ""]
        lines += [f"- **{r['name']}** ({r.get('source', '')}): {r.get('message', '')}" for r in failed]
        lines.append("")
    path = root / "report.md"
    path.write_text("\n".join(lines))
    return path
