"""The run folder: trajectory, keyframes, map, metrics and resolved config of one run.

Every system writes the same files and the same ``metrics.json`` keys, so runs of different
systems compare directly:

``system, sequence, frames, processed_frames, tracked_frames, prior_frames, posed_frames,
skipped_frames, keyframes, fps_end_to_end, fps_compute, wall_s, compute_s, stage_ms,
stage_ms_total, interrupted, ate_rmse_m`` (``null`` without ground truth or when the evaluation
failed, with ``ate_error`` saying why) and, with ground truth, the ATE/RPE statistics.

``tracked_frames`` counts the frames with a pose estimated from their own data;
``prior_frames`` those whose pose is a motion prior (``SystemOutput.prior_indices``);
``posed_frames`` = both = the poses in ``trajectory.txt``. ``metrics.json`` is strict JSON
(:mod:`torchslam.strictjson`): a non-finite value is written as ``null`` and listed under
``non_finite``.
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
from ..data.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory
from ..environment import environment_info
from ..errors import TorchSlamError
from ..strictjson import dumps as strict_dumps
from ..strictjson import finite_or_none
from ..systems.base import RunResult
from .runfolder import OutputWriteError

__all__ = ["METRIC_KEYS", "write_ply", "write_run"]

logger = logging.getLogger(__name__)

METRIC_KEYS = (
    "system",
    "sequence",
    "frames",
    "processed_frames",
    "tracked_frames",
    "prior_frames",
    "posed_frames",
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
    return finite_or_none(x)


# The headline figures are evo's: ``evo_ape tum groundtruth.txt trajectory.txt -a`` and
# ``evo_rpe tum groundtruth.txt trajectory.txt -a --delta 1 --delta_unit f`` on the files.
HEADLINE_ALIGN = "se3"
EXACT = "exact"


def _evaluate(estimate: Trajectory, reference: Trajectory, max_dt: float) -> tuple[dict[str, Any] | None, str | None]:
    """ATE and RPE (rigid alignment, 1-frame pairs, evo's association): (flat metrics, None) or (None, why not)."""
    from ..eval import EvaluationError, ate, metrics_dict, rpe

    try:
        a = ate(estimate, reference, align=HEADLINE_ALIGN, max_dt=max_dt, association="nearest")
        r = rpe(estimate, reference, delta=1, unit="frames", align=HEADLINE_ALIGN, max_dt=max_dt, association="nearest")
    except EvaluationError as exc:  # e.g. no timestamps in common
        return None, str(exc)
    except (RuntimeError, ValueError) as exc:  # the alignment's SVD on overflowing values
        return None, f"non-finite values in the evaluation ({exc.__class__.__name__}: {str(exc).splitlines()[0]})"
    if not all(math.isfinite(v) for v in a.stats.values()):
        return None, (
            f"non-finite ATE (rmse {a.stats['rmse']}): the ground truth or the estimate holds values too large "
            "to evaluate in float64"
        )
    return metrics_dict(a, r), None


def evaluate_against_groundtruth(
    estimate: Trajectory,
    groundtruth: Trajectory | None,
    groundtruth_raw: Trajectory | None = None,
    estimate_at_frames: Trajectory | None = None,
) -> dict[str, Any]:
    """The run's accuracy figures, as ``metrics.json`` records them.

    With ``groundtruth_raw`` (the sequence's ``groundtruth.txt`` as read) the headline
    ``ate_rmse_m`` and the RPE are evo's on the raw file: SE(3) alignment, evo's association
    (nearest timestamp within ``EVO_MAX_DT`` = 0.01 s, no offset), so they equal
    ``evo_ape tum groundtruth.txt trajectory.txt -a`` when ``estimate`` is ``trajectory.txt`` as
    written; ``ate_rmse_interpolated_m`` is the ATE against ``groundtruth`` (the ground truth
    interpolated at the frame timestamps). Without it (synthetic sequences) ``groundtruth``
    holds the exact pose at each frame timestamp and the association is exact (same stamp).
    ``estimate_at_frames`` (default ``estimate``) is the estimate at the unrounded frame
    timestamps, for the exact association of the interpolated variant.

    Keys: ``groundtruth`` (bool), ``ate_rmse_m`` (None without ground truth or when the
    evaluation failed), ``ate_groundtruth`` (``"groundtruth.txt"`` or ``"sequence"``),
    ``ate_association`` (``"nearest"`` or ``"exact"``), ``ate_association_max_dt_s``, the
    ATE/RPE statistics of :func:`torchslam.eval.metrics_dict`, and on failure ``ate_error``
    (also as ``eval_note``): why no ATE could be computed, e.g. non-finite values.
    """
    from ..eval import EVO_MAX_DT, ate

    if groundtruth_raw is not None and len(groundtruth_raw):
        reference, max_dt, association, source = groundtruth_raw, EVO_MAX_DT, "nearest", "groundtruth.txt"
    elif groundtruth is not None and len(groundtruth):
        reference, max_dt, association, source = groundtruth, 0.0, EXACT, "sequence"
    else:
        return {"ate_rmse_m": None, "groundtruth": False}
    out: dict[str, Any] = {
        "groundtruth": True,
        "ate_rmse_m": None,
        "ate_groundtruth": source,
        "ate_association": association,
        "ate_association_max_dt_s": max_dt,
    }
    if len(estimate) < 3:
        out["eval_note"] = f"{len(estimate)} estimated pose(s): the SE(3) alignment needs at least 3"
        return out
    figures, error = _evaluate(estimate, reference, max_dt)
    if error is not None:
        out["ate_error"] = out["eval_note"] = error
        return out
    out.update(figures)
    out["ate_association"] = association
    if reference is groundtruth_raw and groundtruth is not None and len(groundtruth):
        try:
            at_frames = estimate if estimate_at_frames is None else estimate_at_frames
            interp = ate(at_frames, groundtruth, align=HEADLINE_ALIGN, max_dt=0.0)
            out["ate_rmse_interpolated_m"] = finite_or_none(interp.stats["rmse"])
        except (TorchSlamError, RuntimeError, ValueError):
            out["ate_rmse_interpolated_m"] = None
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
    n_prior = 0 if o.prior_indices is None else len(o.prior_indices)
    metrics: dict[str, Any] = {
        "system": system,
        "sequence": sequence.name,
        "frames": result.frames_total,
        "processed_frames": result.frames_processed,
        # A pose from the frame's own data; frames that took a motion prior are counted apart.
        "tracked_frames": len(o.frame_indices) - n_prior,
        "prior_frames": n_prior,
        "posed_frames": len(o.frame_indices),
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
    raw = sequence.groundtruth_raw
    # The headline is evo's on the files: the estimate as trajectory.txt holds it (1e-9 m, 1 us).
    on_disk = read_tum_trajectory(out / "trajectory.txt") if raw is not None and "trajectory.txt" in written else estimate
    metrics.update(evaluate_against_groundtruth(on_disk, sequence.groundtruth, raw, estimate_at_frames=estimate))
    metrics.update(o.metrics)
    if hasattr(sequence, "depth_time_offset"):
        # A TUM folder's depth latency as given, or as ``data.depth_time_offset`` auto estimated it.
        metrics["depth_time_offset_s"] = float(sequence.depth_time_offset)
    if extra:
        metrics.update(extra)
    metrics["environment"] = environment_info()
    text = strict_dumps(metrics)
    attempt("metrics.json", lambda p: p.write_text(text + "\n"))
    if failed:
        raise OutputWriteError(out, written, failed)
    return json.loads(text)
