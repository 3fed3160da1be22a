"""FastGO: global registration of keyframes from per-pair second-order statistics (GC-SLAM back-end)."""

from .linearize import PairLinearization, assemble, linearize, pair_cost, residual_curvature
from .loops import LoopDecision, accept_loop_closures, accept_loop_closures_batch
from .optimize import (
    FastGOBatchResult,
    FastGOConfig,
    FastGOProblem,
    FastGOResult,
    PairStatus,
    optimize,
    optimize_batch,
    pair_status,
)
from .stats import PairStats

__all__ = [
    "FastGOBatchResult",
    "FastGOConfig",
    "FastGOProblem",
    "FastGOResult",
    "LoopDecision",
    "PairLinearization",
    "PairStats",
    "PairStatus",
    "accept_loop_closures",
    "accept_loop_closures_batch",
    "assemble",
    "linearize",
    "optimize",
    "optimize_batch",
    "pair_cost",
    "pair_status",
    "residual_curvature",
]
