"""Resuming a batch: which run folders already hold a complete run of this request, which hold
one of another request (refused unless ``--overwrite``), and the files a redone folder loses.

A run is complete when its ``metrics.json`` says so and its ``trajectory.txt`` agrees; it is
this request's when the system, the data, ``max_frames`` and the resolved config (the device
aside) are the same.
"""

from __future__ import annotations

import copy
import json
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ...config import config_to_dict, load_yaml
from ...data.trajectory import read_tum_trajectory
from ...errors import ConfigError, TorchSlamError
from ..runfolder import OutputFolderError, is_run_file
from .sources import BatchSource
from .summary import as_count

__all__ = ["clear_files", "completed_run", "refuse_replacing_other_requests", "run_files", "run_state", "sequence_config"]

logger = logging.getLogger(__name__)


def sequence_config(resolved: Mapping[str, Any], source: BatchSource, device: str) -> dict[str, Any]:
    """The config ``source``'s run folder records: the resolved one, with its synthetic settings and ``device``."""
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
    metrics, why, _ = run_state(Path(folder), system, spec, config, max_frames)
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


def run_state(
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
    if as_count(metrics.get("processed_frames")) is None:
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


def run_files(folder: Path) -> list[Path]:
    """The files of an earlier run in ``folder`` (anything else there is left alone)."""
    if not folder.is_dir():
        return []
    return [p for p in folder.iterdir() if is_run_file(p.name) and p.is_file()]


def clear_files(files: Iterable[Path]) -> None:
    """Remove ``files`` (those already gone are fine)."""
    for f in files:
        f.unlink(missing_ok=True)


def refuse_replacing_other_requests(
    out: Path, system: str, sources: list[BatchSource], configs: Mapping[int, Mapping[str, Any]], max_frames: int | None
) -> None:
    """Raise OutputFolderError naming the run folders that hold a complete run of another request.

    Args:
        out: the batch folder.
        system: the system's registry name.
        sources: the batch's sequences.
        configs: per sequence index, the config its run folder records (:func:`sequence_config`).
        max_frames: the batch's frame limit.
    """
    differing = []
    for src in sources:
        folder = out / src.name
        if src.error is not None or not folder.is_dir():
            continue
        _, why, complete = run_state(folder, system, src.spec, configs[src.index], max_frames)
        if complete and why is not None:
            differing.append(f"{src.name} ({why})")
    if differing:
        raise OutputFolderError(
            f"--out {out}: {len(differing)} run folder(s) hold a complete run of another request that this batch "
            f"would replace: {', '.join(differing)}; pass --overwrite to redo them, or choose another --out"
        )
