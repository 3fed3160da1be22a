"""Trajectory evaluation: timestamp association, ATE, RPE and their reports."""

from .metrics import (
    AlignMode,
    ATEResult,
    Association,
    DeltaUnit,
    EVO_MAX_DT,
    EvaluationError,
    RPEResult,
    associate_trajectories,
    ate,
    error_statistics,
    rpe,
    rpe_pairs,
)
from .report import format_report, metrics_dict

__all__ = [
    "AlignMode",
    "ATEResult",
    "Association",
    "DeltaUnit",
    "EVO_MAX_DT",
    "EvaluationError",
    "RPEResult",
    "associate_trajectories",
    "ate",
    "error_statistics",
    "format_report",
    "metrics_dict",
    "rpe",
    "rpe_pairs",
]
