"""SO(3) and SE(3): exponential and logarithm maps, composition, inverse, action, adjoint.

Convention:
    Poses are ``(..., 4, 4)`` homogeneous transforms; ``T_ab`` maps frame-b points into frame a.
    A twist is ``xi = (rho, phi)`` with the translational part first. Updates are
    left-multiplicative: ``T <- se3_exp(xi) @ T``.

Every function accepts any leading batch shape, float32 or float64, and keeps the input's
dtype and device. Small angles switch to Taylor series chosen from one per-dtype table, and the
divisor is made safe *before* dividing so gradients stay finite at the identity.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import broadcast_shape, check_float, check_shape

__all__ = [
    "skew",
    "vex",
    "so3_exp",
    "so3_log",
    "so3_angle",
    "se3_exp",
    "se3_exp_numpy",
    "se3_log",
    "se3_log_numpy",
    "se3_inverse",
    "se3_inverse_numpy",
    "se3_compose",
    "se3_act",
    "se3_adjoint",
    "se3_from_Rt",
    "SMALL_ANGLE",
]

# Squared-angle thresholds below which the Taylor branches are used. Series are kept to the
# theta^6 term, so their truncation error is below the dtype's round-off at these thresholds,
# while the closed forms lose no more than ~1e-12 (float64) to cancellation just above them.
SMALL_ANGLE = {torch.float64: 0.05**2, torch.float32: 0.2**2}
# Above this cosine the rotation is treated as "near pi" in so3_log (sin(theta) is tiny there).
_NEAR_PI_COS = -0.9


def _check(x: Tensor, spec: str, name: str) -> None:
    check_shape(x, spec, name)
    check_float(x, name)


def so3_angle(R: Tensor) -> Tensor:
    """Rotation angle in [0, pi] of ``(..., 3, 3)`` matrices, accurate near 0 and near pi.

    ``atan2(sin, cos)`` with ``2 sin = ||vex(R - R^T)||`` and ``2 cos = tr R - 1`` avoids the
    loss of precision of ``acos`` near 0 (about 1e-8 rad) that a 1e-6 degree tolerance would see.
    """
    a = R - R.transpose(-1, -2)
    sin2 = torch.stack([a[..., 2, 1], a[..., 0, 2], a[..., 1, 0]], dim=-1).norm(dim=-1)
    cos2 = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1
    return torch.atan2(sin2, cos2)


def skew(v: Tensor) -> Tensor:
    """Return the cross-product matrix ``[v]x`` with ``[v]x @ u == cross(v, u)``.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    _check(v, "... 3", "v")
    return _skew(v)


def _skew(v: Tensor) -> Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def vex(S: Tensor) -> Tensor:
    """Return the vector of the skew-symmetric part of ``S`` (inverse of :func:`skew`).

    Args:
        S: (..., 3, 3) matrices; only ``(S - S^T) / 2`` is used.

    Returns:
        (..., 3) vectors.
    """
    _check(S, "... 3 3", "S")
    return _vex(S)


def _vex(S: Tensor) -> Tensor:
    return 0.5 * torch.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]], dim=-1
    )


def _eye(like: Tensor, n: int = 3) -> Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device)


def _coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Return A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 for t^2 = ``theta2``."""
    small = theta2 < SMALL_ANGLE[theta2.dtype]
    t2 = torch.where(small, torch.ones_like(theta2), theta2)  # safe before sqrt and division
    t = t2.sqrt()
    s, c = torch.sin(t), torch.cos(t)
    A = torch.where(small, 1 - theta2 / 6 * (1 - theta2 / 20 * (1 - theta2 / 42)), s / t)
    B = torch.where(small, 0.5 - theta2 / 24 * (1 - theta2 / 30 * (1 - theta2 / 56)), (1 - c) / t2)
    C = torch.where(small, 1 / 6 - theta2 / 120 * (1 - theta2 / 42 * (1 - theta2 / 72)), (t - s) / (t2 * t))
    return A, B, C


def so3_exp(phi: Tensor) -> Tensor:
    """Map rotation vectors to rotation matrices (Rodrigues).

    Args:
        phi: (..., 3) axis-angle vectors, radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    _check(phi, "... 3", "phi")
    return _so3_exp(phi)


def _so3_exp(phi: Tensor) -> Tensor:
    theta2 = (phi * phi).sum(-1)
    A, B, _ = _coefficients(theta2)
    W = _skew(phi)
    return _eye(phi) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def so3_log(R: Tensor) -> Tensor:
    """Map rotation matrices to rotation vectors with angle in [0, pi].

    Stable near the identity (series in sin^2) and near pi (axis from the symmetric part).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors, radians.
    """
    _check(R, "... 3 3", "R")
    return _so3_log(R)


def _so3_log(R: Tensor) -> Tensor:
    v = _vex(R)  # sin(theta) * axis
    s2 = (v * v).sum(-1)
    c = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    small = (s2 < SMALL_ANGLE[R.dtype]) & (c > 0)
    near_pi = c < _NEAR_PI_COS
    # Generic branch: theta / sin(theta) from atan2, with a safe sin^2 so the masked lanes stay finite.
    s2_safe = torch.where(small | near_pi, torch.ones_like(s2), s2)
    s = s2_safe.sqrt()
    f_generic = torch.atan2(s, c) / s
    # Small branch: asin(s) / s = 1 + s^2/6 + 3 s^4/40 + 5 s^6/112 + 35 s^8/1152.
    f_small = 1 + s2 / 6 * (1 + s2 * 9 / 20 * (1 + s2 * 25 / 42 * (1 + s2 * 49 / 72)))
    phi = torch.where(small, f_small, f_generic)[..., None] * v
    # Near pi: (R + R^T)/2 - cos(theta) I = (1 - cos theta) n n^T; take its strongest column.
    Bm = 0.5 * (R + R.transpose(-1, -2)) - c[..., None, None] * _eye(R)
    diag = torch.diagonal(Bm, dim1=-2, dim2=-1)
    k = diag.argmax(-1, keepdim=True)
    col = torch.gather(Bm, -1, k[..., None, :].expand(Bm.shape[:-1] + (1,))).squeeze(-1)
    n = col / col.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(R.dtype).tiny)
    sign = torch.where((n * v).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(R.dtype)
    theta = torch.atan2(torch.where(near_pi, s2, torch.ones_like(s2)).sqrt(), c)
    phi_pi = sign * n * theta[..., None]
    return torch.where(near_pi[..., None], phi_pi, phi)


def se3_from_Rt(R: Tensor, t: Tensor) -> Tensor:
    """Assemble ``(..., 4, 4)`` transforms from rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    _check(R, "... 3 3", "R")
    _check(t, "... 3", "t")
    return _from_Rt(R, t)


def _from_Rt(R: Tensor, t: Tensor) -> Tensor:
    batch = broadcast_shape(R.shape[:-2], t.shape[:-1], what="the batch shapes of R and t")
    T = R.new_zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def se3_exp(xi: Tensor) -> Tensor:
    """Map twists ``(rho, phi)`` to rigid transforms.

    Args:
        xi: (..., 6) twists, translation part first (metres, radians).

    Returns:
        (..., 4, 4) transforms.
    """
    _check(xi, "... 6", "xi")
    return _se3_exp(xi)


def _se3_exp(xi: Tensor) -> Tensor:
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1)
    A, B, C = _coefficients(theta2)
    W = _skew(phi)
    W2 = W @ W
    eye = _eye(xi)
    R = eye + A[..., None, None] * W + B[..., None, None] * W2
    V = eye + B[..., None, None] * W + C[..., None, None] * W2
    return _from_Rt(R, (V @ rho[..., None])[..., 0])


def se3_log(T: Tensor) -> Tensor:
    """Map rigid transforms to twists ``(rho, phi)`` with rotation angle in [0, pi].

    Args:
        T: (..., 4, 4) transforms.

    Returns:
        (..., 6) twists, translation part first.
    """
    _check(T, "... 4 4", "T")
    return _se3_log(T)


def _se3_log(T: Tensor) -> Tensor:
    R, t = T[..., :3, :3], T[..., :3, 3]
    phi = _so3_log(R)
    theta2 = (phi * phi).sum(-1)
    small = theta2 < SMALL_ANGLE[T.dtype]
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    th = t2.sqrt()
    # V^-1 = I - W/2 + D W^2 with D = (1 - (t/2) cot(t/2)) / t^2.
    D = torch.where(
        small,
        1 / 12 + theta2 / 720 * (1 + theta2 / 42 * (1 + theta2 / 40)),
        (1 - 0.5 * th * torch.sin(th) / (1 - torch.cos(th))) / t2,
    )
    W = _skew(phi)
    Vinv = _eye(T) - 0.5 * W + D[..., None, None] * (W @ W)
    rho = (Vinv @ t[..., None])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def se3_inverse(T: Tensor) -> Tensor:
    """Invert rigid transforms using the transpose of the rotation block.

    Args:
        T: (..., 4, 4) transforms ``T_ab``.

    Returns:
        (..., 4, 4) transforms ``T_ba``.
    """
    _check(T, "... 4 4", "T")
    Rt = T[..., :3, :3].transpose(-1, -2)
    return _from_Rt(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def se3_compose(T_ab: Tensor, T_bc: Tensor) -> Tensor:
    """Compose ``T_ac = T_ab @ T_bc`` (broadcasting leading dims).

    Args:
        T_ab: (..., 4, 4) transforms.
        T_bc: (..., 4, 4) transforms.

    Returns:
        (..., 4, 4) transforms ``T_ac``.
    """
    _check(T_ab, "... 4 4", "T_ab")
    _check(T_bc, "... 4 4", "T_bc")
    R = T_ab[..., :3, :3] @ T_bc[..., :3, :3]
    t = (T_ab[..., :3, :3] @ T_bc[..., :3, 3:4])[..., 0] + T_ab[..., :3, 3]
    return _from_Rt(R, t)


def se3_act(T_ab: Tensor, points_b: Tensor) -> Tensor:
    """Transform points from frame b into frame a.

    Args:
        T_ab: (..., 4, 4) rigid transforms.
        points_b: (..., N, 3) points in frame b, metres.

    Returns:
        (..., N, 3) points in frame a.
    """
    _check(T_ab, "... 4 4", "T_ab")
    _check(points_b, "... N 3", "points_b")
    R = T_ab[..., None, :3, :3]
    return (R @ points_b[..., None])[..., 0] + T_ab[..., None, :3, 3]


def se3_adjoint(T: Tensor) -> Tensor:
    """Return the adjoint ``Ad_T`` with ``T exp(xi) T^-1 = exp(Ad_T xi)`` for ``(rho, phi)`` twists.

    Args:
        T: (..., 4, 4) transforms.

    Returns:
        (..., 6, 6) matrices ``[[R, [t]x R], [0, R]]``.
    """
    _check(T, "... 4 4", "T")
    R, t = T[..., :3, :3], T[..., :3, 3]
    Ad = T.new_zeros(T.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., :3, 3:] = _skew(t) @ R
    return Ad


def se3_exp_numpy(xi: np.ndarray) -> np.ndarray:
    """(B, 4, 4) ``exp`` of (B, 6) float64 twists ``(rho, phi)`` in NumPy, as :func:`se3_exp` (the
    same closed form and small-angle series): the host paths' few small updates, where torch's
    fixed cost per operation dominates."""
    if xi.shape[0] == 1:
        return _se3_exp_one(xi[0])[None]
    rho, phi = xi[:, :3], xi[:, 3:]
    theta2 = (phi * phi).sum(-1)
    small = theta2 < SMALL_ANGLE[torch.float64]
    t2 = np.where(small, 1.0, theta2)
    t = np.sqrt(t2)
    s, c = np.sin(t), np.cos(t)
    A = np.where(small, 1 - theta2 / 6 * (1 - theta2 / 20 * (1 - theta2 / 42)), s / t)
    Bc = np.where(small, 0.5 - theta2 / 24 * (1 - theta2 / 30 * (1 - theta2 / 56)), (1 - c) / t2)
    C = np.where(small, 1 / 6 - theta2 / 120 * (1 - theta2 / 42 * (1 - theta2 / 72)), (t - s) / (t2 * t))
    W = _skew_numpy(phi)
    W2 = W @ W
    eye = np.eye(3)
    R = eye + A[:, None, None] * W + Bc[:, None, None] * W2
    V = eye + Bc[:, None, None] * W + C[:, None, None] * W2
    out = np.zeros((xi.shape[0], 4, 4))
    out[:, :3, :3] = R
    out[:, :3, 3] = (V @ rho[..., None])[..., 0]
    out[:, 3, 3] = 1.0
    return out


def _se3_exp_one(xi: np.ndarray) -> np.ndarray:
    """(4, 4) ``exp`` of one float64 twist ``(rho, phi)``: :func:`se3_exp_numpy` in Python scalars."""
    r0, r1, r2, a, b, c = (float(v) for v in xi)
    theta2 = a * a + b * b + c * c
    if theta2 < SMALL_ANGLE[torch.float64]:
        A = 1 - theta2 / 6 * (1 - theta2 / 20 * (1 - theta2 / 42))
        Bc = 0.5 - theta2 / 24 * (1 - theta2 / 30 * (1 - theta2 / 56))
        C = 1 / 6 - theta2 / 120 * (1 - theta2 / 42 * (1 - theta2 / 72))
    else:
        t = math.sqrt(theta2)
        sn, cs = math.sin(t), math.cos(t)
        A, Bc, C = sn / t, (1 - cs) / theta2, (t - sn) / (theta2 * t)
    # W = [phi]x and W^2 = phi phi^T - theta^2 I, entry by entry.
    ab, ac, bc = a * b, a * c, b * c
    d0, d1, d2 = -(b * b + c * c), -(a * a + c * c), -(a * a + b * b)
    R = ((1 + Bc * d0, -A * c + Bc * ab, A * b + Bc * ac),
         (A * c + Bc * ab, 1 + Bc * d1, -A * a + Bc * bc),
         (-A * b + Bc * ac, A * a + Bc * bc, 1 + Bc * d2))
    V = ((1 + C * d0, -Bc * c + C * ab, Bc * b + C * ac),
         (Bc * c + C * ab, 1 + C * d1, -Bc * a + C * bc),
         (-Bc * b + C * ac, Bc * a + C * bc, 1 + C * d2))
    t0, t1, t2 = (v0 * r0 + v1 * r1 + v2 * r2 for v0, v1, v2 in V)
    return np.array([[*R[0], t0], [*R[1], t1], [*R[2], t2], [0.0, 0.0, 0.0, 1.0]])


def se3_log_numpy(T: np.ndarray) -> np.ndarray:
    """(B, 6) twists ``(rho, phi)`` of (B, 4, 4) float64 rigid transforms in NumPy, as
    :func:`se3_log` (the same branches: the series near the identity, the axis from the symmetric
    part near pi): the host paths' per-frame pose algebra, where torch's fixed cost per operation
    dominates."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)  # sin(theta) axis
    s2 = (v * v).sum(-1)
    c = np.clip((R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1) / 2, -1.0, 1.0)
    small = (s2 < SMALL_ANGLE[torch.float64]) & (c > 0)
    near_pi = c < _NEAR_PI_COS
    s = np.sqrt(np.where(small | near_pi, 1.0, s2))
    f = np.where(small, 1 + s2 / 6 * (1 + s2 * 9 / 20 * (1 + s2 * 25 / 42 * (1 + s2 * 49 / 72))), np.arctan2(s, c) / s)
    phi = f[:, None] * v
    if near_pi.any():
        Bm = 0.5 * (R + R.transpose(0, 2, 1)) - c[:, None, None] * np.eye(3)
        k = np.diagonal(Bm, axis1=-2, axis2=-1).argmax(-1)
        col = Bm[np.arange(len(k)), :, k]
        n = col / np.maximum(np.linalg.norm(col, axis=-1, keepdims=True), np.finfo(np.float64).tiny)
        sign = np.where((n * v).sum(-1, keepdims=True) < 0, -1.0, 1.0)
        theta = np.arctan2(np.sqrt(np.where(near_pi, s2, 1.0)), c)
        phi = np.where(near_pi[:, None], sign * n * theta[:, None], phi)
    theta2 = (phi * phi).sum(-1)
    small = theta2 < SMALL_ANGLE[torch.float64]
    t2 = np.where(small, 1.0, theta2)
    th = np.sqrt(t2)
    with np.errstate(divide="ignore", invalid="ignore"):  # the masked lanes only
        D = np.where(small, 1 / 12 + theta2 / 720 * (1 + theta2 / 42 * (1 + theta2 / 40)),
                     (1 - 0.5 * th * np.sin(th) / (1 - np.cos(th))) / t2)
    W = _skew_numpy(phi)
    Vinv = np.eye(3) - 0.5 * W + D[:, None, None] * (W @ W)
    return np.concatenate([(Vinv @ t[..., None])[..., 0], phi], -1)


def se3_inverse_numpy(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) inverses of float64 rigid transforms in NumPy, as :func:`se3_inverse` (the
    transpose of the rotation block)."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def _skew_numpy(phi: np.ndarray) -> np.ndarray:
    """(B, 3, 3) ``[phi]x`` of (B, 3) vectors in NumPy."""
    a, b, c = phi[:, 0], phi[:, 1], phi[:, 2]
    z = np.zeros_like(a)
    return np.stack([z, -c, b, c, z, -a, -b, a, z], -1).reshape(-1, 3, 3)
