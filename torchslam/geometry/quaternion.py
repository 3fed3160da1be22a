"""Unit quaternions in xyzw order (the TUM RGB-D order) and rotation matrices.

Convention:
    Quaternions are ``(..., 4)`` as ``(qx, qy, qz, qw)`` and always named ``quat_xyzw``.
    ``rotmat_to_quat_xyzw`` returns the representative with ``qw >= 0``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import check_float, check_shape

__all__ = ["quat_xyzw_to_rotmat", "rotmat_to_quat_xyzw", "quat_xyzw_slerp"]


def quat_xyzw_to_rotmat(quat_xyzw: Tensor) -> Tensor:
    """Convert quaternions to rotation matrices; the input is normalised first.

    Args:
        quat_xyzw: (..., 4) quaternions ``(qx, qy, qz, qw)``, any non-zero norm.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    check_shape(quat_xyzw, "... 4", "quat_xyzw")
    check_float(quat_xyzw, "quat_xyzw")
    q = quat_xyzw / quat_xyzw.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat_xyzw(R: Tensor) -> Tensor:
    """Convert rotation matrices to unit quaternions with ``qw >= 0``.

    Uses Shepperd's method: of the four candidate formulas, each lane takes the one whose
    divisor (2 sqrt(1 + trace) or 2 sqrt(1 + 2 R_kk - trace)) is largest, so no lane divides
    by a small number.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) quaternions ``(qx, qy, qz, qw)``.
    """
    check_shape(R, "... 3 3", "R")
    check_float(R, "R")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # Four times the square of each component (up to a common factor): pick the largest.
    cand = torch.stack([1 + 2 * m00 - tr, 1 + 2 * m11 - tr, 1 + 2 * m22 - tr, 1 + tr], dim=-1)
    k = cand.argmax(-1)
    d = 2 * cand.clamp_min(torch.finfo(R.dtype).tiny).sqrt()  # (..., 4): 4 * |component|
    qx = torch.stack([d[..., 0] / 4, (m01 + m10) / d[..., 1], (m02 + m20) / d[..., 2], (m21 - m12) / d[..., 3]], -1)
    qy = torch.stack([(m01 + m10) / d[..., 0], d[..., 1] / 4, (m12 + m21) / d[..., 2], (m02 - m20) / d[..., 3]], -1)
    qz = torch.stack([(m02 + m20) / d[..., 0], (m12 + m21) / d[..., 1], d[..., 2] / 4, (m10 - m01) / d[..., 3]], -1)
    qw = torch.stack([(m21 - m12) / d[..., 0], (m02 - m20) / d[..., 1], (m10 - m01) / d[..., 2], d[..., 3] / 4], -1)
    idx = k[..., None]
    q = torch.cat([torch.gather(c, -1, idx) for c in (qx, qy, qz, qw)], dim=-1)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def quat_xyzw_slerp(q0_xyzw: Tensor, q1_xyzw: Tensor, alpha: Tensor) -> Tensor:
    """Spherically interpolate between unit quaternions along the shorter arc.

    Args:
        q0_xyzw: (..., 4) start quaternions.
        q1_xyzw: (..., 4) end quaternions.
        alpha: (...) interpolation parameters in [0, 1].

    Returns:
        (..., 4) unit quaternions.
    """
    check_shape(q0_xyzw, "... 4", "q0_xyzw")
    check_shape(q1_xyzw, "... 4", "q1_xyzw")
    q0 = q0_xyzw / q0_xyzw.norm(dim=-1, keepdim=True)
    q1 = q1_xyzw / q1_xyzw.norm(dim=-1, keepdim=True)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    a = alpha[..., None].to(q0.dtype)
    omega = torch.acos(dot)
    so = torch.sin(omega)
    close = so < 1e-6
    so_safe = torch.where(close, torch.ones_like(so), so)
    w0 = torch.where(close, 1 - a, torch.sin((1 - a) * omega) / so_safe)
    w1 = torch.where(close, a, torch.sin(a * omega) / so_safe)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)
