"""A cloud's full pose against a keyframe's orthographic map: the rotation KCC does not measure.

NI-SLAM's correlators measure translation only; the rotation comes from the attitude, whose
heading drifts with the gyro's bias and which no accelerometer corrects. Where two keyframes
see the same place (a loop), a few Gauss-Newton steps over the old keyframe's fused
orthographic map measure the relative pose, rotation included, from the correlator's answer.

Residuals, per point ``q = R p + t`` in the map's frame at its orthographic pixel
``(u, v) = (q_x / r + W / 2, q_y / r + H / 2)`` (the map rendered on its own axis, as a
keyframe's is):

* depth, point to the map's surface: ``r_d = q_z - D(u, v)``, ``dr_d/dq = n = (-D_u / r, -D_v / r, 1)``;
* grey: ``r_g = g - G(u, v)``, ``dr_g/dq = m = (-G_u / r, -G_v / r, 0)``;

``D`` and ``G`` bilinear in the map, ``D_u`` … that interpolant's derivatives. A left
perturbation ``q <- exp(w) q + v`` moves a point by ``v + w x q``, so a residual with gradient
``a`` has the Jacobian row ``[a, q x a]`` over ``[v, w]``. Each term is scaled by its residuals'
robust spread (1.4826 × their median absolute value), weighted by Huber's kernel at 1.345 of
that spread, and points beyond ``outlier_sigmas`` spreads are left out (depth edges, occlusion).
Steep map surfaces (``|grad D| / r > max_slope``: grazing walls, depth discontinuities that the
bilinear interpolant bridges) are left out of both terms. Coarse to fine over ``levels`` maps
pooled 2 × 2 (a pixel kept where half its block is).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, check_float, check_limits, check_shape
from ..geometry import se3_exp
from ..optim.robust import MAD_TO_SIGMA, robust_cost, robust_weight
from .fusion import KeyframeMap

__all__ = ["MapRefineConfig", "MapRefinement", "refine_against_map"]

_HUBER = 1.345  # Huber's kernel at 95 % Gaussian efficiency, in spreads


@dataclass(frozen=True)
class MapRefineConfig:
    """Settings of ``refine_against_map``.

    Attributes:
        levels: pyramid levels (2 x 2 pooling each), coarsest first.
        finest: the finest level's pooling is ``2 ** finest`` (0: the map itself).
        iterations: Gauss-Newton steps per level.
        max_points: the cloud is thinned by a fixed stride to at most this many points.
        outlier_sigmas: residuals beyond this many robust spreads are left out.
        max_slope: map surfaces steeper than this (depth change per unit of in-plane distance)
            are left out.
        grey: whether the grey residual takes part (the depth residual always does).
        min_points: fewer usable points at the finest level: not converged.
    """

    levels: int = 2
    finest: int = 0
    iterations: int = 8
    max_points: int = 20000
    outlier_sigmas: float = 5.0
    max_slope: float = 3.0
    grey: bool = True
    min_points: int = 500

    LIMITS: ClassVar[dict[str, Limit]] = {
        "levels": AT_LEAST_1, "finest": NON_NEGATIVE, "iterations": AT_LEAST_1, "max_points": AT_LEAST_1,
        "outlier_sigmas": POSITIVE, "max_slope": POSITIVE, "min_points": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        check_limits(self)


@dataclass(frozen=True)
class MapRefinement:
    """Result of ``refine_against_map``, per batch item.

    Attributes:
        T: (B, 4, 4) float64 refined transform from the cloud's frame into the map's.
        covariance: (B, 6, 6) float64 covariance of a left perturbation ``[v, w]`` of ``T``: the
            inverse of the last Gauss-Newton matrix, residuals scaled by their spreads. It treats
            the points' errors as independent, so it is a lower bound.
        count: (B,) long points used in the last step.
        depth_rmse: (B,) float64 RMS of the used depth residuals in the last step, metres.
        converged: (B,) bool: at least ``min_points`` points, and the damping at the end under
            1e3 (the last steps still lowered the cost, instead of being refused again and again).
    """

    T: Tensor
    covariance: Tensor
    count: Tensor
    depth_rmse: Tensor
    converged: Tensor


def _pool(fields: Tensor, valid: Tensor, f: int) -> tuple[Tensor, Tensor]:
    """(B, C, H/f, W/f) mean of (B, C, H, W) ``fields`` over the valid pixels of each f x f block, holes filled.

    A block is kept where half its pixels are valid. An orthographic map is sparse where the
    cloud is coarser than the map (a point per pixel at most), so a pixel left empty then takes
    the mean of its valid 3 x 3 neighbours where at least two are (the bilinear interpolant
    needs four valid corners). Returns the fields and (B, H/f, W/f) validity.
    """
    w = valid.to(fields.dtype)[:, None]
    if f == 1:
        s, c = fields * w, w
    else:
        s = F.avg_pool2d(fields * w, f)
        c = F.avg_pool2d(w, f)
    ok = c >= 0.5
    mean = torch.where(ok, s / c.clamp_min(0.5), torch.zeros_like(s))
    k = ok.to(fields.dtype)
    s3 = F.avg_pool2d(mean * k, 3, stride=1, padding=1, count_include_pad=True)
    c3 = F.avg_pool2d(k, 3, stride=1, padding=1, count_include_pad=True)
    fill = ~ok & (c3 >= 2 / 9 - 1e-6)
    return torch.where(fill, s3 / c3.clamp_min(1 / 9), mean), (ok | fill)[:, 0]


def _bilinear(fields: Tensor, valid: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Bilinear values and derivatives of (B, C, H, W) ``fields`` at image coordinates (B, N).

    Pixel ``i`` covers ``[i, i + 1)``, so its value sits at ``i + 0.5``. Returns values, d/du,
    d/dv (B, C, N) and (B, N) bool: all four neighbours inside and valid.
    """
    B, C, H, W = fields.shape
    s, t = u - 0.5, v - 0.5
    i0, j0 = torch.floor(s), torch.floor(t)
    a, b = (s - i0)[:, None], (t - j0)[:, None]
    inside = (i0 >= 0) & (i0 <= W - 2) & (j0 >= 0) & (j0 <= H - 2)
    idx = (j0.clamp(0, H - 2) * W + i0.clamp(0, W - 2)).long()  # (B, N)
    flat_f = fields.flatten(2)
    flat_v = valid.flatten(1)
    corners = []
    ok = inside
    for off in (0, 1, W, W + 1):
        k = idx + off
        corners.append(flat_f.gather(2, k[:, None].expand(B, C, -1)))
        ok = ok & flat_v.gather(1, k)
    f00, f01, f10, f11 = corners  # (row, column) offsets: 01 is one column right
    val = (1 - b) * ((1 - a) * f00 + a * f01) + b * ((1 - a) * f10 + a * f11)
    d_u = (1 - b) * (f01 - f00) + b * (f11 - f10)
    d_v = (1 - a) * (f10 - f00) + a * (f11 - f01)
    return val, d_u, d_v, ok


def _spread(r: Tensor, use: Tensor, floor: float) -> Tensor:
    """(B,) robust spread of the used residuals (1.4826 x median |r|), at least ``floor``."""
    a = torch.where(use, r.abs(), torch.full_like(r, math.nan))
    med = torch.nanmedian(a, dim=1).values.nan_to_num(nan=floor)
    return (MAD_TO_SIGMA * med).clamp_min(floor)


def _normal_terms(J: Tensor, r: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Gauss-Newton matrix (B, 6, 6) and gradient (B, 6) of weighted rows ``J`` (B, N, 6)."""
    Jw = J * w[..., None]
    return torch.einsum("bni,bnj->bij", Jw, J), torch.einsum("bni,bn->bi", Jw, r)


def refine_against_map(
    points: Tensor,
    grey: Tensor,
    valid: Tensor,
    kf_map: KeyframeMap,
    resolution: Tensor,
    T_init: Tensor,
    cfg: MapRefineConfig = MapRefineConfig(),
) -> MapRefinement:
    """Refine the transform of a cloud into a keyframe's orthographic map (all six degrees of freedom).

    Args:
        points: (B, N, 3) camera-frame points of the cloud, metres.
        grey: (B, N) their grey values, on the map's scale.
        valid: (B, N) bool.
        kf_map: the keyframes' fused orthographic maps, (B, H, W) fields, rendered on their own
            axis (``orthographic_project`` with ``center`` None), in the frame ``T`` maps into.
        resolution: (B,) the maps' resolutions ``r_k``, metres per pixel.
        T_init: (B, 4, 4) the starting transform, cloud frame into map frame (a loop's
            verified ``T_jk``).
        cfg: settings.

    Returns:
        MapRefinement (float64).
    """
    dims: dict[str, int] = {}
    check_shape(points, "B N 3", "points", dims)
    check_shape(grey, "B N", "grey", dims)
    check_shape(valid, "B N", "valid", dims)
    check_shape(kf_map.depth, "B H W", "kf_map.depth", dims)
    check_shape(resolution, "B", "resolution", dims)
    check_shape(T_init, "B 4 4", "T_init", dims)
    for x, name in ((points, "points"), (grey, "grey"), (resolution, "resolution"), (T_init, "T_init")):
        check_float(x, name)
    f64 = torch.float64
    B, N, _ = points.shape
    H, W = kf_map.depth.shape[-2:]
    top = 2 ** (cfg.finest + cfg.levels - 1)
    if H % top or W % top:
        raise ConfigError(f"MapRefineConfig.levels, finest: pooling by {top} needs a map size divisible by it, got {H} x {W}")
    step = max(1, math.ceil(N / cfg.max_points))
    p = points[:, ::step].to(f64)
    g = grey[:, ::step].to(f64)
    pv = valid[:, ::step] & p.isfinite().all(-1)
    # Valid points first in each row (their order kept), the columns no row needs dropped.
    order = torch.argsort((~pv).to(torch.uint8), dim=1, stable=True)[:, : max(1, int(pv.sum(1).max()))]
    p, g, pv = p.gather(1, order[..., None].expand(-1, -1, 3)), g.gather(1, order), pv.gather(1, order)
    p = torch.where(pv[..., None], p, torch.zeros_like(p))
    T = T_init.to(f64).clone()
    r = resolution.to(f64)[:, None]
    fields = torch.stack([kf_map.depth, kf_map.grey], dim=1)  # (B, 2, H, W), pooled in the map's dtype
    eye = torch.eye(6, dtype=f64, device=p.device)
    for level in reversed(range(cfg.finest, cfg.finest + cfg.levels)):
        f = 2**level
        pooled, ok_l = _pool(fields, kf_map.valid, f)
        lv = _Level(pooled.to(f64), ok_l, r * f, p, g, pv, cfg)
        _, normal, scales = lv.cost(T)
        ev = normal()
        lam = torch.full((B,), 1e-4, dtype=f64, device=p.device)
        for _ in range(cfg.iterations):
            A = ev.H + lam[:, None, None] * torch.diag_embed(ev.H.diagonal(dim1=-2, dim2=-1)) + 1e-12 * eye
            delta = -torch.linalg.solve(A, ev.grad[..., None])[..., 0]
            T_try = se3_exp(delta) @ T
            cost, normal, _ = lv.cost(T_try, scales)
            better = cost < ev.cost
            lam = torch.where(better, lam / 3, lam * 4).clamp(1e-7, 1e7)
            if not bool(better.any()):
                continue  # every row keeps its point: no normal equations at the rejected one
            trial = normal()
            T = torch.where(better[:, None, None], T_try, T)
            ev = _Eval(*(torch.where(better.view(-1, *([1] * (a.dim() - 1))), a, b) for a, b in zip(trial, ev)))
    cov = torch.linalg.inv(ev.H + 1e-12 * eye)
    converged = (lam < 1e3) & (ev.count >= cfg.min_points)
    return MapRefinement(T=T, covariance=cov, count=ev.count, depth_rmse=ev.rmse, converged=converged)


class _Eval(NamedTuple):
    cost: Tensor  # (B,) truncated robust cost
    H: Tensor  # (B, 6, 6)
    grad: Tensor  # (B, 6)
    count: Tensor  # (B,) depth residuals used
    rmse: Tensor  # (B,) their RMS, metres


class _Level:
    """One pyramid level's map and the thinned cloud: residuals, cost, normal equations."""

    def __init__(self, fields: Tensor, ok: Tensor, r: Tensor, p: Tensor, g: Tensor, pv: Tensor, cfg: MapRefineConfig):
        self.fields, self.ok, self.r, self.p, self.g, self.pv, self.cfg = fields, ok, r, p, g, pv, cfg
        self.H, self.W = fields.shape[-2:]

    def residuals(self, T: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Depth and grey residuals (B, N), their gradients in q (B, N, 3), the points q and where usable."""
        q = torch.einsum("bij,bnj->bni", T[:, :3, :3], self.p) + T[:, None, :3, 3]
        r = self.r
        u = q[..., 0] / r + self.W / 2
        v = q[..., 1] / r + self.H / 2
        val, d_u, d_v, ok = _bilinear(self.fields, self.ok, u, v)
        use = ok & self.pv & ((d_u[:, 0].square() + d_v[:, 0].square()).sqrt() / r <= self.cfg.max_slope)
        n = torch.stack([-d_u[:, 0] / r, -d_v[:, 0] / r, torch.ones_like(u)], dim=-1)
        m = torch.stack([-d_u[:, 1] / r, -d_v[:, 1] / r, torch.zeros_like(u)], dim=-1)
        return q[..., 2] - val[:, 0], self.g - val[:, 1], n, m, q, use

    def cost(
        self, T: Tensor, scales: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Callable[[], _Eval], tuple[Tensor, Tensor]]:
        """(B,) truncated Huber cost at ``T`` (a point unusable or beyond ``outlier_sigmas`` costs the
        cap), a function that completes it with the normal equations there, and the residuals'
        (B, 1) robust spreads it used: ``scales``, or those at ``T`` (held over a level)."""
        r_d, r_g, n, m, q, use = self.residuals(T)
        if scales is None:
            scales = _spread(r_d, use, 1e-4)[:, None], _spread(r_g, use, 1e-3)[:, None]
        terms = [(r_d, n, scales[0])] + ([(r_g, m, scales[1])] if self.cfg.grey else [])
        c = self.cfg.outlier_sigmas
        cap = robust_cost(q.new_full((1, 1), c), "huber", _HUBER)
        cost = q.new_zeros(q.shape[0])
        kept = []
        for r, a, s in terms:
            z = r.abs() / s  # in spreads
            keep = use & (z <= c)
            cost = cost + torch.where(keep, robust_cost(z, "huber", _HUBER), cap).sum(1)
            kept.append((r, a, s, z, keep))

        def normal() -> _Eval:
            Hm = q.new_zeros(q.shape[0], 6, 6)
            grad = q.new_zeros(q.shape[0], 6)
            for r, a, s, z, keep in kept:
                w = keep * robust_weight(z, "huber", _HUBER) / s.square()
                h, gr = _normal_terms(torch.cat([a, _cross(q, a)], dim=-1), r, w)
                Hm, grad = Hm + h, grad + gr
            keep_d = kept[0][4]
            count = keep_d.sum(1)
            rmse = (torch.where(keep_d, r_d, torch.zeros_like(r_d)).square().sum(1) / count.clamp_min(1)).sqrt()
            return _Eval(cost, Hm, grad, count, rmse)

        return cost, normal, scales


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """(..., 3) cross products, written out (``torch.cross`` is slower on small last dimensions)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)
