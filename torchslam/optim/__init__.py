"""Batched Gauss-Newton / Levenberg-Marquardt machinery, block-sparse solves and robust kernels."""

from .blocksparse import (
    BlockCholeskyFactor,
    BlockCholeskySymbolic,
    BlockSparseMatrix,
    SolverMethod,
    analyze,
    block_cholesky,
    pcg_block_jacobi,
    solve_block_sparse,
)
from .lm import LMConfig, LMResult, levenberg_marquardt_se3
from .robust import RobustKernel, robust_cost, robust_weight

__all__ = [
    "BlockCholeskyFactor",
    "BlockCholeskySymbolic",
    "BlockSparseMatrix",
    "LMConfig",
    "LMResult",
    "RobustKernel",
    "SolverMethod",
    "analyze",
    "block_cholesky",
    "levenberg_marquardt_se3",
    "pcg_block_jacobi",
    "robust_cost",
    "robust_weight",
    "solve_block_sparse",
]
