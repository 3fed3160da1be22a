"""Batched Gauss-Newton / Levenberg-Marquardt machinery, block-sparse solves, robust kernels and
the per-pair 6x6 Gauss-Newton solve and the log-space parametrisation of learned positive values."""

from .blocksparse import (
    BlockCholeskyFactor,
    BlockCholeskySymbolic,
    BlockSparseMatrix,
    Schedule,
    SolverMethod,
    analyze,
    block_cholesky,
    pcg_block_jacobi,
    solve_block_sparse,
)
from .lm import LMConfig, LMResult, levenberg_marquardt_se3
from .pairsolve import PairStep, solve_pair_steps
from .positive import positive_parameter, positive_value
from .robust import MAD_TO_SIGMA, RobustKernel, robust_cost, robust_weight

__all__ = [
    "MAD_TO_SIGMA",
    "BlockCholeskyFactor",
    "BlockCholeskySymbolic",
    "BlockSparseMatrix",
    "LMConfig",
    "LMResult",
    "PairStep",
    "RobustKernel",
    "Schedule",
    "SolverMethod",
    "analyze",
    "block_cholesky",
    "levenberg_marquardt_se3",
    "pcg_block_jacobi",
    "positive_parameter",
    "positive_value",
    "robust_cost",
    "robust_weight",
    "solve_block_sparse",
    "solve_pair_steps",
]
