"""The run folder: trajectory, keyframes, map, metrics and resolved config of one run.

Every system writes the same files and the same ``metrics.json`` keys, so runs of different
systems compare directly:

``system, sequence, frames, processed_frames, tracked_frames, skipped_frames, keyframes,
fps_end_to_end, fps_compute, wall_s, compute_s, stage_ms, stage_ms_total, interrupted,
ate_rmse_m`` (``null`` without ground truth) and, with ground truth, the ATE/RPE statistics.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.frame import Sequence
from ..data.trajectory import Trajectory, write_tum_trajectory
from ..environment import environment_info
from .base import RunResult
from .runfolder import OutputWriteError

__all__ = ["METRIC_KEYS", "voxel_downsample", "write_ply", "write_run"]

logger = logging.getLogger(__name__)

METRIC_KEYS = (
    "system",
    "sequence",
    "frames",
    "processed_frames",
    "tracked_frames",
    "skipped_frames",
    "keyframes",
    "fps_end_to_end",
    "fps_compute",
    "wall_s",
    "compute_s",
    "stage_ms",
    "stage_ms_total",
    "interrupted",
    "ate_rmse_m",
)


def voxel_downsample(points: torch.Tensor, colors: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Average the points and colours that fall into the same cubic voxel.

    Args:
        points: (P, 3) world points, metres.
        colors: (P, 3) colours in [0, 1].
        voxel: voxel edge, metres (<= 0: no downsampling).

    Returns:
        (points (Q, 3) float32, colors (Q, 3) float32), Q <= P, ordered by voxel key.
    """
    P = points.to(torch.float64)
    C = colors.to(torch.float64)
    if voxel > 0 and len(P):
        key = torch.floor(P / voxel).to(torch.int64)
        # One int64 per voxel, ordered as the (x, y, z) rows lexicographically: a 1-D unique is
        # ~20x faster than ``unique(dim=0)`` over rows (0.8 s for 2.6M points on one CPU core).
        key = key - key.min(0).values
        span = key.max(0).values + 1
        if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:
            flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
            _, inv = torch.unique(flat, return_inverse=True)
        else:
            _, inv = torch.unique(key, dim=0, return_inverse=True)
        n = int(inv.max()) + 1
        cnt = torch.zeros(n, dtype=torch.float64, device=P.device).index_add_(0, inv, torch.ones_like(P[:, 0]))
        P = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, P) / cnt[:, None]
        C = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, C) / cnt[:, None]
    return P.float(), C.float()


def write_ply(path: str | os.PathLike, points: torch.Tensor, colors: torch.Tensor | None = None) -> None:
    """Write points ``(P, 3)`` (and colours ``(P, 3)`` in [0, 1]) as a binary little-endian PLY."""
    pts = points.detach().cpu().to(torch.float32).numpy()
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}",
              "property float x", "property float y", "property float z"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        c = (colors.detach().cpu().to(torch.float32).clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())


def _finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def evaluate_against_groundtruth(estimate: Trajectory, groundtruth: Trajectory | None) -> dict[str, Any]:
    """ATE (rigid alignment) and RPE (1 frame) of ``estimate`` against ``groundtruth``."""
    from ..eval import ate, metrics_dict, rpe

    if groundtruth is None or len(groundtruth) == 0:
        return {"ate_rmse_m": None, "groundtruth": False}
    if len(estimate) < 2:
        return {"ate_rmse_m": None, "groundtruth": True, "eval_note": "fewer than 2 estimated poses"}
    try:
        a = ate(estimate, groundtruth, align="se3")
        r = rpe(estimate, groundtruth, delta=1, unit="frames", align="se3")
    except ValueError as exc:  # e.g. no timestamps in common
        return {"ate_rmse_m": None, "groundtruth": True, "eval_note": str(exc)}
    out = {"groundtruth": True}
    out.update(metrics_dict(a, r))
    return out


def write_run(
    out_dir: str | os.PathLike,
    system: str,
    result: RunResult,
    sequence: Sequence,
    config: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the run folder and return the metrics written to ``metrics.json``.

    Args:
        out_dir: the run folder (created if missing).
        system: the system's name.
        result: what ``run_sequence`` returned.
        sequence: the sequence that was processed (for ground truth and names).
        config: the resolved configuration, saved as ``config.yaml``.
        extra: more metrics to record (e.g. the attitude source, the device).

    Raises:
        OutputWriteError: some files could not be written (a full disk, a read-only folder);
            every other file was still written and the error names both.
    """
    import yaml

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputWriteError(out, [], [("", f"cannot create the folder ({exc.strerror or exc})")]) from exc
    written: list[str] = []
    failed: list[tuple[str, str]] = []

    def attempt(name: str, write: Callable[[Path], None]) -> None:
        # A full disk or another write error loses one file, not the run: the rest is still written.
        try:
            write(out / name)
        except OSError as exc:
            logger.error("%s: cannot write (%s)", out / name, exc.strerror or exc)
            failed.append((name, exc.strerror or str(exc)))
            try:  # a half-written file would pass for a result
                (out / name).unlink(missing_ok=True)
            except OSError:
                pass
        else:
            written.append(name)

    o = result.output
    estimate = Trajectory(o.timestamps.to(torch.float64), o.T_wc.to(torch.float64))
    attempt("trajectory.txt", lambda p: write_tum_trajectory(
        p, estimate, header=f"torchslam {system} estimate of {sequence.name} (camera-to-world)"))
    kf_times = sequence.timestamps[o.keyframe_indices] if len(o.keyframe_indices) else torch.zeros(0, dtype=torch.float64)
    attempt("keyframes.txt", lambda p: write_tum_trajectory(
        p,
        Trajectory(kf_times.to(torch.float64), o.keyframe_T_wc.to(torch.float64)),
        header=f"torchslam {system} keyframes of {sequence.name} (camera-to-world)",
    ))
    if o.map_points is not None and len(o.map_points):
        attempt("map.ply", lambda p: write_ply(p, o.map_points, o.map_colors))
    if config is not None:
        attempt("config.yaml", lambda p: p.write_text(yaml.safe_dump(dict(config), sort_keys=False)))
    n = max(result.frames_processed, 1)
    metrics: dict[str, Any] = {
        "system": system,
        "sequence": sequence.name,
        "frames": result.frames_total,
        "processed_frames": result.frames_processed,
        "tracked_frames": len(o.frame_indices),
        "skipped_frames": result.frames_skipped,
        "skipped": [{"index": int(i), "reason": r} for i, r in result.skipped],
        "keyframes": len(o.keyframe_indices),
        "fps_end_to_end": _finite(result.fps_end_to_end),
        "fps_compute": _finite(result.fps_compute),
        "wall_s": result.wall_s,
        "compute_s": result.compute_s,
        "stage_ms": {k: v / n for k, v in o.stage_ms.items()},
        "stage_ms_total": dict(o.stage_ms),
        "interrupted": result.interrupted,
    }
    metrics.update(evaluate_against_groundtruth(estimate, sequence.groundtruth))
    metrics.update(o.metrics)
    if extra:
        metrics.update(extra)
    metrics["environment"] = environment_info()
    attempt("metrics.json", lambda p: p.write_text(json.dumps(metrics, indent=2, default=_json_default) + "\n"))
    if failed:
        raise OutputWriteError(out, written, failed)
    return metrics


def _json_default(v: Any) -> Any:
    if isinstance(v, torch.Tensor):
        return v.tolist()
    if isinstance(v, (np.generic,)):
        return v.item()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")
