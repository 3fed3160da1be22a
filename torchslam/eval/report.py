"""Human-readable tables and flat JSON dictionaries of ATE/RPE results."""

from __future__ import annotations

from typing import Any

from ..errors import ShapeError
from .metrics import STAT_KEYS, ATEResult, RPEResult

__all__ = ["format_report", "metrics_dict"]

_TABLE_STATS = ("rmse", "mean", "median", "std", "min", "max")


def _check_results(ate_result: Any, rpe_result: Any) -> None:
    if not isinstance(ate_result, ATEResult):
        raise ShapeError(f"ate_result: expected an ATEResult, got {type(ate_result).__name__}")
    if rpe_result is not None and not isinstance(rpe_result, RPEResult):
        raise ShapeError(f"rpe_result: expected an RPEResult or None, got {type(rpe_result).__name__}")


def format_report(ate_result: ATEResult, rpe_result: RPEResult | None = None) -> str:
    """Render the results as a Markdown table, stating the alignment of every metric.

    Args:
        ate_result: result of :func:`torchslam.eval.ate`.
        rpe_result: optional result of :func:`torchslam.eval.rpe`.

    Returns:
        A few lines of text: an alignment summary, then one table row per metric with
        rmse/mean/median/std/min/max and the unit.
    """
    _check_results(ate_result, rpe_result)
    lines = [
        f"ATE alignment: {ate_result.align} (scale {ate_result.scale:.6f}), {ate_result.matched} matched poses "
        f"(association {ate_result.association}, max dt {ate_result.max_dt:g} s)",
    ]
    if rpe_result is not None:
        pairing = "all pairs" if rpe_result.all_pairs else "consecutive pairs"
        lines.append(
            f"RPE alignment: {rpe_result.align} (scale {rpe_result.scale:.6f}), delta {rpe_result.delta} "
            f"{rpe_result.unit}, {rpe_result.pairs.shape[0]} {pairing} from {rpe_result.matched} matched poses"
        )
    lines.append("")
    lines.append("| metric | align | " + " | ".join(_TABLE_STATS) + " | unit |")
    lines.append("|---|---|" + "---:|" * len(_TABLE_STATS) + "---|")

    def row(name: str, align: str, stats: dict[str, float], unit: str) -> str:
        return f"| {name} | {align} | " + " | ".join(f"{stats[k]:.6f}" for k in _TABLE_STATS) + f" | {unit} |"

    lines.append(row("ATE", ate_result.align, ate_result.stats, "m"))
    if rpe_result is not None:
        lines.append(row("RPE translation", rpe_result.align, rpe_result.trans_stats, "m"))
        lines.append(row("RPE rotation", rpe_result.align, rpe_result.rot_stats, "deg"))
    return "\n".join(lines) + "\n"


def metrics_dict(ate_result: ATEResult, rpe_result: RPEResult | None = None) -> dict[str, Any]:
    """Flatten the results into a JSON-ready dict with unit-suffixed keys.

    Keys: ``ate_{rmse,mean,median,std,min,max}_m``, ``ate_sse_m2``, ``ate_scale``, ``align``
    (the ATE alignment), ``matched``, ``ate_association`` (the rule) and
    ``ate_association_max_dt_s`` (its tolerance, seconds); with an RPE result also
    ``rpe_trans_{stat}_m``, ``rpe_trans_sse_m2``, ``rpe_rot_{stat}_deg``, ``rpe_rot_sse_deg2``,
    ``rpe_align``, ``rpe_scale``, ``rpe_delta``, ``rpe_unit``, ``rpe_all_pairs``, ``rpe_pairs``
    and ``rpe_matched``.

    Args:
        ate_result: result of :func:`torchslam.eval.ate`.
        rpe_result: optional result of :func:`torchslam.eval.rpe`.

    Returns:
        A flat dict of floats, ints, bools and strings.
    """
    _check_results(ate_result, rpe_result)
    out: dict[str, Any] = {}
    for k in STAT_KEYS:
        out["ate_sse_m2" if k == "sse" else f"ate_{k}_m"] = ate_result.stats[k]
    out["ate_scale"] = ate_result.scale
    out["align"] = ate_result.align
    out["matched"] = ate_result.matched
    out["ate_association"] = ate_result.association
    out["ate_association_max_dt_s"] = ate_result.max_dt
    if rpe_result is not None:
        for k in STAT_KEYS:
            out["rpe_trans_sse_m2" if k == "sse" else f"rpe_trans_{k}_m"] = rpe_result.trans_stats[k]
        for k in STAT_KEYS:
            out["rpe_rot_sse_deg2" if k == "sse" else f"rpe_rot_{k}_deg"] = rpe_result.rot_stats[k]
        out["rpe_align"] = rpe_result.align
        out["rpe_scale"] = rpe_result.scale
        out["rpe_delta"] = rpe_result.delta
        out["rpe_unit"] = rpe_result.unit
        out["rpe_all_pairs"] = rpe_result.all_pairs
        out["rpe_pairs"] = int(rpe_result.pairs.shape[0])
        out["rpe_matched"] = rpe_result.matched
    return out
