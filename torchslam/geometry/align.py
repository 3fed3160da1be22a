"""Weighted rigid (and similarity) alignment of point sets: Kabsch / Umeyama, batched."""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import ShapeError, check_float, check_shape
from .lie import _from_Rt

__all__ = ["umeyama_alignment"]


def umeyama_alignment(
    src: Tensor, dst: Tensor, weights: Tensor | None = None, with_scale: bool = False
) -> tuple[Tensor, Tensor]:
    """Find the transform that best maps ``src`` onto ``dst`` in the weighted least-squares sense.

    Minimises ``sum_k w_k || dst_k - (s R src_k + t) ||^2`` (Umeyama 1991). The rotation is
    reflection-safe: the sign of the smallest singular direction is flipped when
    ``det(U V^T) < 0``. With ``with_scale=False`` (Kabsch) ``s = 1``.

    Args:
        src: (B, N, 3) source points.
        dst: (B, N, 3) destination points.
        weights: optional (B, N) non-negative weights; zero weights exclude points (padding).
        with_scale: also estimate a scale ``s`` (Sim(3)).

    Returns:
        T: (B, 4, 4) rigid transforms ``[R | t]`` (the scale is *not* folded into R).
        scale: (B,) scales (ones when ``with_scale`` is False).
        Degenerate sets (fewer than 3 non-collinear weighted points) give a rotation that is
        some valid minimiser; callers that need to know check the weights themselves.
    """
    dims: dict[str, int] = {}
    check_shape(src, "B N 3", "src", dims)
    check_shape(dst, "B N 3", "dst", dims)
    check_float(src, "src")
    if weights is None:
        weights = src.new_ones(src.shape[:2])
    check_shape(weights, "B N", "weights", dims)
    wsum = weights.sum(-1)
    if bool((wsum <= 0).any()):
        raise ShapeError("weights: every batch item needs a positive total weight")
    w = (weights / wsum[:, None]).to(src.dtype)[..., None]  # (B, N, 1)
    mu_s = (w * src).sum(1)
    mu_d = (w * dst).sum(1)
    xs, xd = src - mu_s[:, None], dst - mu_d[:, None]
    cov = (w * xd).transpose(1, 2) @ xs  # (B, 3, 3) = sum w d s^T
    U, S, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones_like(S)
    D[:, 2] = d
    R = U @ (D[..., None] * Vh)
    if with_scale:
        var_s = (w[..., 0] * (xs * xs).sum(-1)).sum(-1)
        scale = (S * D).sum(-1) / var_s.clamp_min(torch.finfo(src.dtype).tiny)
    else:
        scale = torch.ones_like(wsum, dtype=src.dtype)
    t = mu_d - scale[:, None] * (R @ mu_s[..., None])[..., 0]
    return _from_Rt(R, t), scale
