"""Slow reference implementations the tests check the library against (and benchmarks time).

Each one computes what a batched library function computes, by the plain route: a loop over
pairs and hypotheses, or one linearisation per correspondence. They use only the public API.
Benchmarks load this file by path (``scripts/_bench.py``'s ``test_references``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchslam.errors import check_shape
from torchslam.fastgo import PairLinearization
from torchslam.geometry import skew, umeyama_alignment
from torchslam.registration.sparse import SparseConfig, ransac_samples


def ransac_rigid_reference(
    p_i: Tensor,
    p_j: Tensor,
    valid: Tensor,
    cfg: SparseConfig | None = None,
    generator: torch.Generator | None = None,
    block: int = 50,
) -> tuple[Tensor, Tensor]:
    """Loop over pairs and hypotheses doing what :func:`~torchslam.registration.sparse.ransac_rigid` does.

    Consumes the same samples (:func:`ransac_samples` with the same base seed), fits each with
    its own Kabsch call and scores it from explicit residual vectors. The adaptive stopping rule
    (``cfg.ransac_confidence``) is checked in Python floats at the end of every block of
    ``block`` hypotheses: a pair stops once the hypotheses tried reach
    ``log(1 - p) / log(1 - w^s)`` at its best inlier ratio ``w``.

    Args:
        p_i: (B, M, 3) points in frame i, metres.
        p_j: (B, M, 3) matching points in frame j, metres.
        valid: (B, M) bool candidate matches.
        cfg: RANSAC settings (``SparseConfig()`` when None).
        generator: source of the base seed (``cfg.seed`` when None).

    Returns:
        T_ij: (B, 4, 4) best hypotheses (identity for a pair with too few candidates).
        inliers: (B, M) bool inliers of ``T_ij`` among ``valid``.
    """
    cfg = SparseConfig() if cfg is None else cfg
    p_j = p_j.to(p_i.dtype)
    B, M = valid.shape
    idx, ok = ransac_samples(valid, cfg, generator)
    T_out = torch.eye(4, dtype=p_i.dtype, device=p_i.device).expand(B, 4, 4).clone()
    inl_out = torch.zeros_like(valid)
    for b in range(B):
        if not bool(ok[b]) or M == 0:
            continue
        best_count, best_T = -1, None
        for h in range(idx.shape[1]):
            sel = idx[b, h]
            T = umeyama_alignment(p_j[b, sel][None], p_i[b, sel][None])[0][0]
            if not bool(torch.isfinite(T).all()):
                continue
            r = p_j[b] @ T[:3, :3].T + T[:3, 3] - p_i[b]
            inl = valid[b] & (r.norm(dim=-1) / p_i[b, :, 2] < cfg.inlier_threshold)
            count = int(inl.sum())
            if count > best_count:
                best_count, best_T = count, T
            tried = h + 1
            if cfg.ransac_confidence < 1 and (tried % block == 0 or tried == idx.shape[1]):
                w = max(best_count, 0) / max(int(valid[b].sum()), 1)
                if w >= 1:
                    break
                if w > 0 and math.log(1 - cfg.ransac_confidence) / math.log(1 - w**cfg.ransac_sample) <= tried:
                    break
        if best_T is not None:
            T_out[b] = best_T
            r = p_j[b] @ best_T[:3, :3].T + best_T[:3, 3] - p_i[b]
            inl_out[b] = valid[b] & (r.norm(dim=-1) / p_i[b, :, 2] < cfg.inlier_threshold)
    return T_out, inl_out


def reference_linearize(
    T_wc: Tensor,
    pairs: Tensor,
    points_i: Sequence[Tensor],
    points_j: Sequence[Tensor],
    weights: Sequence[Tensor] | None = None,
    chunk: int = 1 << 17,
) -> PairLinearization:
    """Linearise every correspondence and sum per pair (the O(#correspondences) baseline of FastGO).

    Residual ``r = q_i - q_j`` with Jacobians ``J_i = [I, -[q_i]x]``, ``J_j = -[I, -[q_j]x]``
    (FastGO Eqs. (2), (6)); vectorised over correspondences, chunked to bound memory.

    Args:
        T_wc: (N, 4, 4) keyframe poses.
        pairs: (M, 2) int64 keyframe indices.
        points_i: M tensors (K_m, 3) of points in frame i.
        points_j: M tensors (K_m, 3) of the matching points in frame j.
        weights: optional M tensors (K_m,) of correspondence weights.
        chunk: correspondences processed per vectorised step.

    Returns:
        The same quantities as :func:`torchslam.fastgo.linearize`, summed correspondence by
        correspondence.
    """
    check_shape(T_wc, "N 4 4", "T_wc")
    check_shape(pairs, f"{len(points_i)} 2", "pairs")
    dt, dev = T_wc.dtype, T_wc.device
    M = len(points_i)
    pi = torch.cat(list(points_i)).to(dt)
    pj = torch.cat(list(points_j)).to(dt)
    w = None if weights is None else torch.cat(list(weights)).to(dt)
    lengths = torch.tensor([p.shape[0] for p in points_i], device=dev)
    seg = torch.repeat_interleave(torch.arange(M, device=dev), lengths)
    acc = T_wc.new_zeros(M, 6 * 6 * 3 + 12 + 1)
    eye = torch.eye(3, dtype=dt, device=dev)
    for s in range(0, pi.shape[0], chunk):
        sg = seg[s:s + chunk]
        Ti, Tj = T_wc[pairs[sg, 0]], T_wc[pairs[sg, 1]]
        qi = (Ti[:, :3, :3] @ pi[s:s + chunk, :, None])[..., 0] + Ti[:, :3, 3]
        qj = (Tj[:, :3, :3] @ pj[s:s + chunk, :, None])[..., 0] + Tj[:, :3, 3]
        r = qi - qj
        K = r.shape[0]
        Ji = torch.cat([eye.expand(K, 3, 3), -skew(qi)], -1)  # (K, 3, 6)
        Jj = -torch.cat([eye.expand(K, 3, 3), -skew(qj)], -1)
        wk = torch.ones_like(r[:, 0]) if w is None else w[s:s + chunk]
        wJi = wk[:, None, None] * Ji
        wJj = wk[:, None, None] * Jj
        rows = torch.cat(
            [
                (wJi.transpose(-1, -2) @ Ji).reshape(K, 36),
                (wJi.transpose(-1, -2) @ Jj).reshape(K, 36),
                (wJj.transpose(-1, -2) @ Jj).reshape(K, 36),
                (wJi.transpose(-1, -2) @ r[..., None])[..., 0],
                (wJj.transpose(-1, -2) @ r[..., None])[..., 0],
                (wk * (r * r).sum(-1))[:, None],
            ],
            dim=1,
        )
        acc = acc.index_add(0, sg, rows)
    return PairLinearization(
        acc[:, :36].reshape(M, 6, 6), acc[:, 36:72].reshape(M, 6, 6), acc[:, 72:108].reshape(M, 6, 6),
        acc[:, 108:114], acc[:, 114:120], acc[:, 120],
    )


def reference_edge_innovation(
    T_wc: Tensor, i: Tensor, j: Tensor, T_ij: Tensor, information: Tensor,
    new_i: int, new_j: int, new_T_ij: Tensor, new_information: Tensor, fixed: int = 0,
) -> float:
    """Mahalanobis norm of a new edge's innovation against the graph's predicted covariance.

    The linear-Gaussian route, dense and by autograd: the graph's pose covariance
    ``P = (J^T Omega J)^-1`` with node ``fixed`` held (one dense matrix over all free nodes), the
    new edge's residual ``nu`` and Jacobian ``J_new`` at ``T_wc``, and
    ``nu^T (Omega_new^+ + J_new P J_new^T)^+ nu`` restricted to the range of ``Omega_new`` (a
    translation-only edge tests 3 components). float64.
    """
    from torchslam.backend import edge_residuals
    from torchslam.geometry import se3_exp

    n = T_wc.shape[0]
    free = [k for k in range(n) if k != fixed]

    def residuals(delta: Tensor, ii: Tensor, jj: Tensor, T: Tensor) -> Tensor:
        full = T_wc.new_zeros(n, 6)
        full[free] = delta.reshape(len(free), 6)
        return edge_residuals(se3_exp(full) @ T_wc, ii, jj, T)

    d0 = T_wc.new_zeros(6 * len(free))
    J = torch.autograd.functional.jacobian(lambda d: residuals(d, i, j, T_ij), d0).reshape(len(i), 6, -1)
    H = torch.einsum("eak,eab,ebl->kl", J, information, J)
    P = torch.linalg.inv(H)
    ni, nj = torch.tensor([new_i]), torch.tensor([new_j])
    nu = residuals(d0, ni, nj, new_T_ij[None])[0]
    J_new = torch.autograd.functional.jacobian(lambda d: residuals(d, ni, nj, new_T_ij[None])[0], d0)  # (6, 6F)
    evals, evecs = torch.linalg.eigh(new_information)
    U = evecs[:, evals > 1e-12 * evals.max()]  # range of the information
    S = torch.diag(1.0 / evals[evals > 1e-12 * evals.max()]) + U.T @ J_new @ P @ J_new.T @ U
    v = U.T @ nu
    return float(v @ torch.linalg.solve(S, v))
