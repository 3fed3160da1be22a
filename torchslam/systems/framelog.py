"""Bookkeeping both SLAM systems share: the map's voxel grid."""

from __future__ import annotations

import torch

__all__ = ["voxel_downsample"]


def voxel_downsample(points: torch.Tensor, colors: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Average the points and colours that fall into the same cubic voxel.

    Args:
        points: (P, 3) world points, metres.
        colors: (P, 3) colours in [0, 1].
        voxel: voxel edge, metres (<= 0: no downsampling).

    Returns:
        (points (Q, 3) float32, colors (Q, 3) float32), Q <= P, ordered by voxel key.
    """
    P = points.to(torch.float64)
    C = colors.to(torch.float64)
    if voxel > 0 and len(P):
        key = torch.floor(P / voxel).to(torch.int64)
        # One int64 per voxel, ordered as the (x, y, z) rows lexicographically: a 1-D unique is
        # ~20x faster than ``unique(dim=0)`` over rows (0.8 s for 2.6M points on one CPU core).
        key = key - key.min(0).values
        span = key.max(0).values + 1
        if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:
            flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
            _, inv = torch.unique(flat, return_inverse=True)
        else:
            _, inv = torch.unique(key, dim=0, return_inverse=True)
        n = int(inv.max()) + 1
        cnt = torch.zeros(n, dtype=torch.float64, device=P.device).index_add_(0, inv, torch.ones_like(P[:, 0]))
        P = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, P) / cnt[:, None]
        C = torch.zeros(n, 3, dtype=torch.float64, device=P.device).index_add_(0, inv, C) / cnt[:, None]
    return P.float(), C.float()
