"""The per-pair 6x6 Gauss-Newton solve that sparse and dense registration share.

Each of B independent pairs has its own normal equations ``H delta = -g`` in the left twist
``delta = (rho, phi)`` of its relative pose (``T <- se3_exp(delta) @ T``). They are solved by a
batched Cholesky factorisation; a pair whose ``H`` is not positive definite, or whose step is not
finite, takes a zero step and is reported as not solved, so the caller keeps its pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..devices import numpy_viewable
from ..errors import check_float, check_shape

__all__ = ["PairStep", "solve_pair_steps"]


@dataclass(frozen=True)
class PairStep:
    """Gauss-Newton steps of B pairs.

    Attributes:
        delta: (B, 6) steps ``-H^-1 g``, twists ``(rho, phi)``; 0 where not solved.
        solved: (B,) bool, ``H`` positive definite and the step finite.
    """

    delta: Tensor
    solved: Tensor


def solve_pair_steps(H: Tensor, g: Tensor, host: bool = False) -> PairStep:
    """Solve ``H delta = -g`` for each of B pairs by Cholesky factorisation.

    Args:
        H: (B, 6, 6) symmetric Gauss-Newton matrices ``J^T W J``.
        g: (B, 6) gradients ``J^T W r``, same dtype.
        host: solve plain host tensors in NumPy (the same steps to round-off, a tenth of torch's
            fixed cost for a few 6x6 systems). Off by default, so that a device path exercised
            on the host (the synchronisation budgets) runs torch's operations.

    Returns:
        PairStep: the steps, 0 for pairs whose ``H`` is not positive definite or whose step is not
        finite (``solved`` False there).
    """
    dims: dict[str, int] = {}
    check_shape(H, "B 6 6", "H", dims)
    check_shape(g, "B 6", "g", dims)
    check_float(H, "H")
    check_float(g, "g")
    if host and numpy_viewable(H) and numpy_viewable(g) and H.shape[0]:
        step = _solve_numpy(H, g)
        if step is not None:
            return step
    L, info = torch.linalg.cholesky_ex(H)
    solved = info == 0
    # A failed factor is replaced by the identity so that its (discarded) solve stays finite;
    # every pair's solve is independent of the others'.
    L = torch.where(solved[:, None, None], L, torch.eye(6, dtype=H.dtype, device=H.device).expand_as(L))
    delta = -torch.cholesky_solve(g[..., None], L)[..., 0]
    solved = solved & torch.isfinite(delta).all(-1)
    return PairStep(torch.where(solved[:, None], delta, torch.zeros_like(delta)), solved)


def _solve_numpy(H: Tensor, g: Tensor) -> PairStep | None:
    """The steps in NumPy on the host (a tenth of torch's fixed cost for a few 6x6 systems), or
    None when some ``H`` is not finite or not positive definite, or its solve fails (NumPy then
    fails for the whole batch; torch's path tells which pairs)."""
    Hn, gn = H.numpy(), g.numpy()
    if not (np.isfinite(Hn).all() and np.isfinite(gn).all()):
        return None  # NumPy's Cholesky does not reject NaN; torch's path marks those pairs
    try:
        np.linalg.cholesky(Hn)
        delta = -np.linalg.solve(Hn, gn[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    solved = np.isfinite(delta).all(-1)
    delta = np.where(solved[:, None], delta, 0.0)
    return PairStep(torch.from_numpy(delta), torch.from_numpy(solved))
