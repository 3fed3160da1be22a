"""FastGO linearisation: Gauss-Newton blocks of every frame pair from its statistics.

Correspondence k of pair (i, j) has world points ``q_i = R_i p_i + t_i``, ``q_j = R_j p_j + t_j``
and residual ``r = q_i - q_j`` (FastGO Eq. (2)). With the left perturbation
``T <- exp(delta) T`` the Jacobians are ``J_i = [I, -[q_i]x]`` and ``J_j = -[I, -[q_j]x]``
(Eq. (6)). Summed over the pair, every block is linear in the statistics (Eqs. (18)-(20)):

    Q_i  = R_i s_i + n t_i                                         (sum q_i)
    M_ab = R_a S_ab R_b^T + (R_a s_a) t_b^T + t_a (R_b s_b)^T + n t_a t_b^T   (sum q_a q_b^T)
    K(M) = M^T - tr(M) I                    (sum [a]x [b]x  for M = sum a b^T)
    H_ii = [[n I, -[Q_i]x], [[Q_i]x, -K(M_ii)]]                   H_jj likewise
    H_ij = -[[n I, -[Q_j]x], [[Q_i]x, -K(M_ij)]]                  H_ji = H_ij^T
    g_i  = [Q_i - Q_j ; -vex(M_ij^T - M_ij)],   g_j = -g_i
    cost = tr M_ii + tr M_jj - 2 tr M_ij

The cost is evaluated in the equivalent centred form
``n |mean residual|^2 + tr C_ii + tr C_jj - 2 tr(R_i C_ij R_j^T)`` (``C`` the moments about the
pair's centroids), which loses far fewer digits when the poses are far from the world origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ShapeError, check_float, check_shape
from ..geometry.lie import _skew, _vex
from ..optim.blocksparse import BlockSparseMatrix
from .stats import PairStats

__all__ = ["PairLinearization", "linearize", "pair_cost", "assemble", "residual_curvature"]


@dataclass(frozen=True)
class PairLinearization:
    """Gauss-Newton blocks of M frame pairs (``H = J^T J``, ``g = J^T r`` over each pair).

    Attributes:
        H_ii: (M, 6, 6) block of pose i with itself.
        H_ij: (M, 6, 6) block coupling pose i (rows) and pose j (columns).
        H_jj: (M, 6, 6) block of pose j.
        g_i: (M, 6) gradient half for pose i.
        g_j: (M, 6) gradient half for pose j (``-g_i``).
        cost: (M,) sum of squared residuals, square metres.
    """

    H_ii: Tensor
    H_ij: Tensor
    H_jj: Tensor
    g_i: Tensor
    g_j: Tensor
    cost: Tensor


def _check_inputs(T_wc: Tensor, pairs: Tensor, stats: PairStats) -> None:
    check_shape(T_wc, "N 4 4", "T_wc")
    check_float(T_wc, "T_wc")
    check_shape(pairs, f"{len(stats)} 2", "pairs")
    if pairs.dtype != torch.int64:
        raise ShapeError(f"pairs: expected int64 keyframe indices, got {pairs.dtype}")


def _blocks(T_wc: Tensor, pairs: Tensor, stats: PairStats, with_curvature: bool = False):
    dt = T_wc.dtype
    Ti, Tj = T_wc[pairs[:, 0]], T_wc[pairs[:, 1]]
    Ri, ti, Rj, tj = Ti[:, :3, :3], Ti[:, :3, 3], Tj[:, :3, :3], Tj[:, :3, 3]
    n = stats.n.to(dt)
    a_i = (Ri @ stats.s_i.to(dt)[..., None])[..., 0]  # (M, 3) R_i s_i
    a_j = (Rj @ stats.s_j.to(dt)[..., None])[..., 0]
    Q_i = a_i + n[:, None] * ti
    Q_j = a_j + n[:, None] * tj

    def moment(RS: Tensor, Rb: Tensor, Qa: Tensor, tb: Tensor, ta: Tensor, ab: Tensor) -> Tensor:
        # M_ab = R_a S_ab R_b^T + Q_a t_b^T + t_a (R_b s_b)^T   (Q_a = R_a s_a + n t_a)
        return RS @ Rb.transpose(-1, -2) + Qa[:, :, None] * tb[:, None, :] + ta[:, :, None] * ab[:, None, :]

    M_ij = moment(Ri @ stats.S_ij.to(dt), Rj, Q_i, tj, ti, a_j)
    M_ii = moment(Ri @ stats.S_ii.to(dt), Ri, Q_i, ti, ti, a_i)
    M_jj = moment(Rj @ stats.S_jj.to(dt), Rj, Q_j, tj, tj, a_j)
    g_rot = -_vex(M_ij.transpose(-1, -2) - M_ij)  # M^T - M is skew, so _vex is exact here
    g_i = torch.cat([Q_i - Q_j, g_rot], dim=-1)
    eye = torch.eye(3, dtype=dt, device=T_wc.device)
    nI = n[:, None, None] * eye

    def K(M: Tensor) -> Tensor:
        return M.transpose(-1, -2) - torch.diagonal(M, dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye

    Wi, Wj = _skew(Q_i), _skew(Q_j)

    def block(tl: Tensor, tr: Tensor, bl: Tensor, br: Tensor) -> Tensor:
        return torch.cat([torch.cat([tl, tr], -1), torch.cat([bl, br], -1)], -2)

    H_ii = block(nI, -Wi, Wi, -K(M_ii))
    H_jj = block(nI, -Wj, Wj, -K(M_jj))
    H_ij = -block(nI, -Wj, Wi, -K(M_ij))
    if not with_curvature:
        return (H_ii, H_ij, H_jj), g_i, M_ij

    def curvatures() -> tuple[Tensor, Tensor]:
        # Residual curvature of the left perturbation: exp(d) q = q + d^q + d^d^q / 2 + ...,
        # with d^d^q = phi x (phi x q) + phi x rho, so sum_k r_k . d^d^q_k is the quadratic
        # form of [[0, [R]x / 2], [-[R]x / 2, sym(A) - tr(A) I]] with A = sum r q^T,
        # R = sum r. Only poses i and j themselves are involved (no coupling block); pose j
        # enters with -r.
        zero = torch.zeros_like(nI)

        def curvature(A: Tensor, R: Tensor) -> Tensor:
            half = 0.5 * _skew(R)
            sym = 0.5 * (A + A.transpose(-1, -2)) - torch.diagonal(A, dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye
            return block(zero, half, -half, sym)

        return curvature(M_ii - M_ij.transpose(-1, -2), Q_i - Q_j), curvature(M_jj - M_ij, Q_j - Q_i)

    # The curvature is returned as a closure: callers that do not need it pay nothing.
    return (H_ii, H_ij, H_jj), g_i, M_ij, curvatures


def pair_cost(T_wc: Tensor, pairs: Tensor, stats: PairStats) -> Tensor:
    """Return each pair's sum of squared residuals ``sum w |T_i p_i - T_j p_j|^2`` (FastGO Eq. (1)).

    Args:
        T_wc: (N, 4, 4) keyframe poses, camera to world.
        pairs: (M, 2) int64 keyframe indices (i, j).
        stats: statistics of the M pairs.

    Returns:
        (M,) costs in square metres, clamped at 0 against round-off.
    """
    _check_inputs(T_wc, pairs, stats)
    return _pair_cost(T_wc, pairs, stats)


def _centred(stats: PairStats, dtype: torch.dtype) -> tuple[Tensor, ...]:
    """``(n, [mean_i | C_ij] (M, 3, 4), mean_j (M, 3, 1), tr C_ii + tr C_jj)``: the pose-independent
    part of the cost, packed for two batched products per evaluation."""
    st = stats.to(dtype=dtype)
    mi, mj, C_ii, C_ij, C_jj = st.centred()
    tr = torch.diagonal(C_ii, dim1=-2, dim2=-1).sum(-1) + torch.diagonal(C_jj, dim1=-2, dim2=-1).sum(-1)
    return st.n, torch.cat([mi[..., None], C_ij], -1), mj[..., None].contiguous(), tr


def _pair_cost(T_wc: Tensor, pairs: Tensor, stats: PairStats, cen: tuple[Tensor, ...] | None = None) -> Tensor:
    n, A_i, mj, tr = cen if cen is not None else _centred(stats, T_wc.dtype)
    P = T_wc.index_select(0, pairs.reshape(-1)).view(-1, 2, 4, 4)
    Ri, Rj = P[:, 0, :3, :3], P[:, 1, :3, :3]
    X = torch.bmm(Ri, A_i)  # (M, 3, 4): [R_i mean_i | R_i C_ij]
    d = X[:, :, 0] + P[:, 0, :3, 3] - torch.bmm(Rj, mj)[:, :, 0] - P[:, 1, :3, 3]
    cross = (X[:, :, 1:] * Rj).sum((-1, -2))  # tr(R_i C_ij R_j^T)
    return (n * (d * d).sum(-1) + tr - 2 * cross).clamp_min(0)


def linearize(T_wc: Tensor, pairs: Tensor, stats: PairStats) -> PairLinearization:
    """Linearise all frame pairs at once from their statistics (O(M), no loop over pairs).

    Args:
        T_wc: (N, 4, 4) keyframe poses, camera to world, float32/64 (float64 recommended).
        pairs: (M, 2) int64 keyframe indices (i, j) of each pair; ``stats`` are in their frames.
        stats: statistics of the M pairs.

    Returns:
        The per-pair blocks, gradient halves and costs (FastGO Eqs. (8)-(9), (18)-(20)).
    """
    _check_inputs(T_wc, pairs, stats)
    (H_ii, H_ij, H_jj), g_i, _ = _blocks(T_wc, pairs, stats)
    return PairLinearization(H_ii, H_ij, H_jj, g_i, -g_i, _pair_cost(T_wc, pairs, stats))


def residual_curvature(T_wc: Tensor, pairs: Tensor, stats: PairStats) -> tuple[Tensor, Tensor]:
    """Second-order residual terms of each pair, from the statistics (O(M)).

    The exact Hessian of the cost ``c(delta) = sum |exp(d_i) q_i - exp(d_j) q_j|^2`` at
    ``delta = 0`` is ``2 (J^T J + S)``; Gauss-Newton drops ``S``. It only touches the diagonal
    blocks of poses i and j.

    Args:
        T_wc: (N, 4, 4) keyframe poses.
        pairs: (M, 2) int64 keyframe indices.
        stats: statistics of the M pairs.

    Returns:
        ``(S_i, S_j)``, each (M, 6, 6) symmetric.
    """
    _check_inputs(T_wc, pairs, stats)
    return _blocks(T_wc, pairs, stats, with_curvature=True)[3]()


def assemble(lin: PairLinearization, pairs: Tensor, num_nodes: int) -> tuple[BlockSparseMatrix, Tensor]:
    """Sum per-pair blocks into the global normal equations ``H delta = -g``.

    Args:
        lin: per-pair linearisation of M pairs.
        pairs: (M, 2) int64 keyframe indices.
        num_nodes: N keyframes.

    Returns:
        ``(H, g)``: the (N-node, 6x6-block) system and (N, 6) gradient.
    """
    i, j = pairs[:, 0], pairs[:, 1]
    dt = lin.H_ii.dtype
    diag = lin.H_ii.new_zeros(num_nodes, 6, 6).index_add(0, i, lin.H_ii).index_add(0, j, lin.H_jj)
    g = lin.g_i.new_zeros(num_nodes, 6).index_add(0, i, lin.g_i).index_add(0, j, lin.g_j)
    return BlockSparseMatrix(diag.to(dt), lin.H_ij, i.contiguous(), j.contiguous()), g
