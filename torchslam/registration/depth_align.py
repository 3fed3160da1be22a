"""A sparse registration's pose refined against the keyframe's depth image.

An ORB registration (:mod:`.sparse`) measures a frame's pose from a few hundred keypoints, each
lifted by the depth of one pixel: corners, where depth is least reliable. Its frame-to-frame
error on TUM fr1/xyz is about twice the dense front-end's (median 3.5 against 1.6 mm). This step
keeps the ORB inliers and adds the frame's depth itself: about ``points`` of the frame's
valid-depth pixels, taken at a square lattice, are moved by the current pose into the keyframe,
where each gives the geometric residual of the dense front-end (DVO's ``r_Z``),

    r_Z = Z_i(pi(q)) - q_z,   q = T p_j,

divided by ``(q_z / 1 m)^2`` (Kinect depth noise grows as ``z^2``). The ORB inliers keep their
3-D residual ``(T p_j - p_i) / z_i`` of :func:`~.sparse.refine_rigid`. Each kind is divided by
its own robust scale, 1.4826 times the median absolute residual (of the three components for the
ORB kind), with the dense front-end's floors, and Huber-weighted (``k = 1.345``; on an ORB
residual's norm ``k sqrt(3)``); one Gauss-Newton step on SE(3) (left update) is taken per
iteration with both kinds in one system, the scales estimated again at every step (so the
steps shrink by about half each: on TUM fr1/xyz the third moves a pose by 0.4 mm at the
median). The depth residuals pin the directions a surface constrains; the ORB ones keep the rest
(a plane alone leaves three directions free).

``Z_i`` is sampled bilinearly where all four neighbours hold depth within
``depth_edge_tolerance`` of each other (the dense front-end's rule for a depth-smooth pixel) and
a depth residual counts where ``|r_Z| < correspondence_threshold * q_z``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..devices import numpy_viewable
from ..geometry import PinholeCamera, distort_planes_with_jacobian, se3_exp, se3_exp_numpy, skew

__all__ = ["sample_depth_points", "refine_with_depth"]

_HUBER_K = 1.345
_MAD = 1.4826


def sample_depth_points(depth: Tensor, rays: Tensor, points: int, min_depth: float, max_depth: float) -> Tensor:
    """(N, 3) float64 points of frame pixels on a square lattice of about ``points`` pixels, where depth is valid.

    Args:
        depth: (1, H, W) depth, metres, 0 = invalid.
        rays: (H*W, 2) undistorted normalised rays of every pixel.
        points: lattice size: every ``s``-th row and column, ``s = max(1, round(sqrt(H W / points)))``
            (the valid-depth share of them is returned).
        min_depth, max_depth: valid depth range, metres.
    """
    H, W = depth.shape[-2:]
    s = max(1, round(math.sqrt(H * W / max(1, points))))
    z = depth.reshape(H, W)[s // 2 :: s, s // 2 :: s].to(torch.float64)
    r = rays.view(H, W, 2)[s // 2 :: s, s // 2 :: s].to(torch.float64)
    keep = (z >= min_depth) & (z <= max_depth)
    zs, r = z[keep], r[keep]
    return torch.stack([r[:, 0] * zs, r[:, 1] * zs, zs], -1)


def _bilinear_depth(depth: Tensor, u: Tensor, v: Tensor, tol: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Depth at (u, v) (N,) pixels, its gradient (per pixel) and where it is depth-smooth."""
    H, W = depth.shape
    u0 = torch.floor(u)
    v0 = torch.floor(v)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 <= W - 2) & (v0 <= H - 2)
    a, b = u - u0, v - v0
    i0 = (v0.clamp(0, H - 2) * W + u0.clamp(0, W - 2)).long()
    flat = depth.reshape(-1)
    z00, z01, z10, z11 = (flat[i0 + k].to(torch.float64) for k in (0, 1, W, W + 1))
    lo = torch.minimum(torch.minimum(z00, z01), torch.minimum(z10, z11))
    hi = torch.maximum(torch.maximum(z00, z01), torch.maximum(z10, z11))
    ok = ok & (lo > 0) & (hi - lo <= tol * lo)
    top, bottom = z00 + (z01 - z00) * a, z10 + (z11 - z10) * a
    z = top + (bottom - top) * b
    gu = (z01 - z00) * (1 - b) + (z11 - z10) * b
    gv = bottom - top
    return z, gu, gv, ok


def _robust(r: Tensor, mask: Tensor, floor: float) -> tuple[Tensor, float]:
    """Huber weights (0 off ``mask``) of residuals ``r`` in units of their robust scale, and the scale."""
    if bool(mask.any()):
        s = max(float(r[mask].abs().median()) * _MAD, floor)
    else:
        s = floor
    e = r.abs() / s
    w = torch.where(e > _HUBER_K, _HUBER_K / e.clamp_min(1e-12), torch.ones_like(e)) * mask
    return w, s


def refine_with_depth(
    T: Tensor, depth_i: Tensor, camera: PinholeCamera, points_j: Tensor,
    orb_i: Tensor, orb_j: Tensor, orb_inliers: Tensor, iterations: int,
    depth_edge_tolerance: float = 0.1, correspondence_threshold: float = 0.02,
    floor_geometric: float = 1e-3, floor_orb: float = 1e-3, min_points: int = 100,
    twist_i: Tensor | None = None, readout: float = 0.0,
) -> tuple[Tensor, int]:
    """Refine ``T`` (4, 4) float64, ``p_i = T p_j``, with frame j's depth points against frame i's depth image.

    Args:
        T: (4, 4) float64 initial pose (the ORB registration's).
        depth_i: (1, H, W) or (H, W) depth of frame i (the keyframe), metres, 0 = invalid.
        camera: frame i's camera (its distortion is applied when projecting).
        points_j: (N, 3) float64 points of frame j (:func:`sample_depth_points`).
        orb_i, orb_j: (M, 3) float64 matched ORB points in frames i and j.
        orb_inliers: (M,) bool, which of them are inliers at ``T``.
        iterations: Gauss-Newton steps.
        depth_edge_tolerance: a depth sample needs its four neighbours within this fraction.
        correspondence_threshold: a depth residual counts where ``|r_Z| < threshold * q_z``.
        floor_geometric: lower bound of the depth residuals' scale (of ``r_Z / z^2``).
        floor_orb: lower bound of the ORB residuals' scale (of ``|r| / z``).
        min_points: with fewer depth residuals counted, ``T`` is returned unchanged.
        twist_i, readout: frame i's rolling shutter (``readout`` seconds from its first row to
            its last, ``twist_i`` (6,) its body twist per second, translation first;
            :mod:`~torchslam.registration.rolling`): each point ``q`` at frame i's stamp is
            compared with the depth its row read, at ``q - delta (w x q + v)`` (``delta`` the
            row's time from the stamp, the row where ``q`` projects). None or 0: a global shutter.
            The Jacobian leaves the small ``delta`` term out.

    Returns:
        The refined pose, and the depth residuals counted at the last step (0: not refined).
    """
    rolling = None if twist_i is None or readout == 0.0 else (twist_i.to(torch.float64).reshape(6), float(readout))
    if all(numpy_viewable(x) for x in (T, depth_i, points_j, orb_i, orb_j, orb_inliers)):
        Tn, used = _refine_numpy(
            T.to(torch.float64).numpy(), depth_i.reshape(depth_i.shape[-2:]).numpy(), camera, points_j.to(torch.float64).numpy(),
            orb_i.to(torch.float64).numpy(), orb_j.to(torch.float64).numpy(), orb_inliers.numpy(), iterations,
            depth_edge_tolerance, correspondence_threshold, floor_geometric, floor_orb, min_points,
            None if rolling is None else (rolling[0].cpu().numpy(), rolling[1]),
        )
        return torch.from_numpy(Tn), used
    depth = depth_i.reshape(depth_i.shape[-2:])
    rows = depth.shape[0]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    dist = camera.distortion if camera.has_distortion else None
    oi = orb_i[orb_inliers].to(torch.float64)
    oj = orb_j[orb_inliers].to(torch.float64)
    inv_zo = 1.0 / oi[:, 2].clamp_min(1e-6)
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=T.device)
    T = T.to(torch.float64)
    used = 0
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        q = points_j @ R.T + t
        if rolling is not None:
            q = _at_row_instant(q, rolling[0].to(q.device), rolling[1], fy, cy, rows)
        z = q[:, 2]
        front = z > 1e-3
        zs = torch.where(front, z, torch.ones_like(z))
        x, y = q[:, 0] / zs, q[:, 1] / zs
        if dist is not None:
            xd, yd, j00, j01, j10, j11 = distort_planes_with_jacobian(x, y, dist)
        else:
            xd, yd = x, y
            j00, j01, j10, j11 = torch.ones_like(x), torch.zeros_like(x), torch.zeros_like(x), torch.ones_like(x)
        u, v = fx * xd + cx, fy * yd + cy
        Zi, gu, gv, ok = _bilinear_depth(depth, u, v, depth_edge_tolerance)
        rz = Zi - z
        ok = ok & front & (rz.abs() < correspondence_threshold * zs)
        n_ok = int(ok.sum())
        if n_ok < min_points:
            return T, used
        used = n_ok
        inv_z = 1.0 / zs
        # d(x, y)/dq, then d(u, v)/dq through the distortion, then dZ_i/dq - e_z.
        dxdq = torch.stack([inv_z, torch.zeros_like(z), -x * inv_z], -1)
        dydq = torch.stack([torch.zeros_like(z), inv_z, -y * inv_z], -1)
        dudq = fx * (j00[:, None] * dxdq + j01[:, None] * dydq)
        dvdq = fy * (j10[:, None] * dxdq + j11[:, None] * dydq)
        a = gu[:, None] * dudq + gv[:, None] * dvdq - ez
        norm = inv_z * inv_z  # residual / z^2
        Jg = torch.cat([a, torch.linalg.cross(q, a)], -1) * norm[:, None]
        rg = rz * norm
        wg, sg = _robust(rg, ok, floor_geometric)
        H = (Jg * (wg / sg**2)[:, None]).T @ Jg
        g = (Jg * (wg / sg**2)[:, None]).T @ rg
        if len(oi):
            qo = oj @ R.T + t
            r_raw = qo - oi  # (M, 3)
            ro = r_raw * inv_zo[:, None]
            # Scale per component (1.4826 MAD of all three), Huber on the norm at k sqrt(3).
            so = max(float(ro.abs().median()) * _MAD, floor_orb)
            e = ro.norm(dim=-1) / so
            wo = torch.where(e > _HUBER_K * 3**0.5, _HUBER_K * 3**0.5 / e.clamp_min(1e-12), torch.ones_like(e))
            c = (wo / so**2) * inv_zo * inv_zo
            # J of component k: [e_k, q x e_k] / z; sum over k of J^T J = [[I, -[q]x], [[q]x, -[q]x^2]] / z^2.
            S0 = c.sum()
            S1 = (c[:, None] * qo).sum(0)
            S2 = (c[:, None, None] * (qo[:, :, None] * qo[:, None, :])).sum(0)
            eye = torch.eye(3, dtype=torch.float64, device=T.device)
            Sx = skew(S1)
            H[:3, :3] += S0 * eye
            H[:3, 3:] += -Sx
            H[3:, :3] += Sx
            H[3:, 3:] += torch.trace(S2) * eye - S2
            cr = c[:, None] * r_raw
            g[:3] += cr.sum(0)
            g[3:] += torch.linalg.cross(qo, cr).sum(0)
        try:
            L = torch.linalg.cholesky(H)
        except RuntimeError:
            return T, 0
        delta = -torch.cholesky_solve(g[:, None], L)[:, 0]
        if not bool(torch.isfinite(delta).all()):
            return T, 0
        T = se3_exp(delta) @ T
    return T, used


def _at_row_instant(q: Tensor, twist: Tensor, readout: float, fy: float, cy: float, rows: int) -> Tensor:
    """(N, 3) points ``q`` at a rolling-shutter frame's stamp moved into the camera of the
    instant its row, the one ``q`` projects to (pinhole rows), was read."""
    zs = q[:, 2].clamp_min(1e-3)
    delta = readout * ((fy * q[:, 1] / zs + cy) - (rows - 1) / 2) / rows
    motion = torch.linalg.cross(twist[3:].expand_as(q), q, dim=-1) + twist[:3]
    return q - delta[:, None] * motion


def _refine_numpy(
    T: np.ndarray, depth: np.ndarray, camera: PinholeCamera, pts: np.ndarray, oi: np.ndarray, oj: np.ndarray,
    inl: np.ndarray, iterations: int, tol: float, thr: float, floor_g: float, floor_o: float, min_points: int,
    rolling: tuple[np.ndarray, float] | None = None,
) -> tuple[np.ndarray, int]:
    """:func:`refine_with_depth` in float64 NumPy on host arrays: the same steps, with the
    coordinates held as planes ``(3, N)`` (a few thousand points, where the count of operations
    sets the time: 1.7 ms for three steps over 2,000 points on one core)."""
    H, W = depth.shape
    flat = depth.reshape(-1)
    P = np.ascontiguousarray(pts.T)  # (3, N)
    oi, oj = oi[inl], oj[inl]
    Oj = np.ascontiguousarray(oj.T)
    Oi = np.ascontiguousarray(oi.T)
    inv_zo2 = 1.0 / np.maximum(Oi[2], 1e-6) ** 2
    kk = _HUBER_K * 3**0.5
    J = np.empty((6, P.shape[1]))
    used = 0
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        rz, ok, inv_z = _depth_terms_numpy(T, P, flat, W, H, camera, tol, thr, J, rolling)
        n_ok = int(np.count_nonzero(ok))
        if n_ok < min_points:
            return T, used
        used = n_ok
        norm = inv_z * inv_z
        sel = np.flatnonzero(ok)
        Jg = J[:, sel] * norm[sel]
        rg = rz[sel] * norm[sel]
        arg = np.abs(rg)
        sg = max(_lower_median(arg) * _MAD, floor_g)
        e = arg / sg
        wg = np.where(e > _HUBER_K, _HUBER_K / np.maximum(e, 1e-12), 1.0) / sg**2
        Jw = Jg * wg
        Hm = Jw @ Jg.T
        g = Jw @ rg
        if Oi.shape[1]:
            qo = R @ Oj
            qo += t[:, None]
            r_raw = qo - Oi  # (3, M)
            ro = r_raw * np.sqrt(inv_zo2)
            so = max(_lower_median(np.abs(ro)) * _MAD, floor_o)
            e = np.sqrt((ro * ro).sum(0)) / so
            c = np.where(e > kk, kk / np.maximum(e, 1e-12), 1.0) / so**2 * inv_zo2
            S0 = c.sum()
            S1 = qo @ c
            S2 = (qo * c) @ qo.T
            Sx = np.array([[0.0, -S1[2], S1[1]], [S1[2], 0.0, -S1[0]], [-S1[1], S1[0], 0.0]])
            Hm[:3, :3] += S0 * np.eye(3)
            Hm[:3, 3:] -= Sx
            Hm[3:, :3] += Sx
            Hm[3:, 3:] += np.trace(S2) * np.eye(3) - S2
            cr = r_raw * c
            g[:3] += cr.sum(1)
            # sum of c q x r, one coordinate at a time
            g[3] += qo[1] @ cr[2] - qo[2] @ cr[1]
            g[4] += qo[2] @ cr[0] - qo[0] @ cr[2]
            g[5] += qo[0] @ cr[1] - qo[1] @ cr[0]
        try:
            np.linalg.cholesky(Hm)  # positive definite, else the pose stays
        except np.linalg.LinAlgError:
            return T, 0
        delta = -np.linalg.solve(Hm, g)
        if not np.isfinite(delta).all():
            return T, 0
        T = se3_exp_numpy(delta[None])[0] @ T
    return T, used


def _depth_terms_numpy(
    T: np.ndarray, P: np.ndarray, flat: np.ndarray, W: int, H: int, camera: PinholeCamera, tol: float, thr: float,
    J: np.ndarray, rolling: tuple[np.ndarray, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The depth residuals ``r_Z`` of points ``P`` (3, N) at ``T`` against the image ``flat``
    (H * W), where they count, and ``1 / q_z``; ``J`` (6, N) receives ``d r_Z / d xi`` (left
    update, translation first), before the division by ``z^2``. ``rolling``: the image's
    (twist, readout), as :func:`refine_with_depth`'s."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    dist = camera.distortion if camera.has_distortion else None
    q = T[:3, :3] @ P
    q += T[:3, 3:]
    if rolling is not None:
        (vx, vy, vz, wx, wy, wz), readout = rolling
        q0, q1, q2 = q
        delta = readout * ((fy * q1 / np.maximum(q2, 1e-3) + cy) - (H - 1) / 2) / H
        q = q - delta * np.stack([wy * q2 - wz * q1 + vx, wz * q0 - wx * q2 + vy, wx * q1 - wy * q0 + vz])
    z = q[2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    inv_z = 1.0 / zs
    x, y = q[0] * inv_z, q[1] * inv_z
    if dist is None:
        xd, yd, j00, j01, j10, j11 = x, y, 1.0, 0.0, 0.0, 1.0
    else:
        xd, yd, j00, j01, j10, j11 = distort_planes_with_jacobian(x, y, dist)
    u, v = fx * xd + cx, fy * yd + cy
    u0, v0 = np.floor(u), np.floor(v)
    ok = front & (u0 >= 0) & (v0 >= 0) & (u0 <= W - 2) & (v0 <= H - 2)
    i0 = (np.clip(v0, 0, H - 2) * W + np.clip(u0, 0, W - 2)).astype(np.int64)
    z00, z01, z10, z11 = flat[i0 + np.array([0, 1, W, W + 1])[:, None]].astype(np.float64)  # (4, N)
    lo = np.minimum(np.minimum(z00, z01), np.minimum(z10, z11))
    hi = np.maximum(np.maximum(z00, z01), np.maximum(z10, z11))
    ok &= (lo > 0) & (hi - lo <= tol * lo)
    a_, b_ = u - u0, v - v0
    top = z00 + (z01 - z00) * a_
    bottom = z10 + (z11 - z10) * a_
    rz = top + (bottom - top) * b_ - z
    ok &= np.abs(rz) < thr * zs
    gu = (z01 - z00) * (1 - b_) + (z11 - z10) * b_
    gv = bottom - top
    # dZ_i/dq - e_z through the projection and the lens model, then [a, q x a].
    cu, cv = gu * fx, gv * fy
    ax = (cu * j00 + cv * j10) * inv_z
    ay = (cu * j01 + cv * j11) * inv_z
    az = -(ax * x + ay * y) - 1.0
    q0, q1, q2 = q
    J[0], J[1], J[2] = ax, ay, az
    J[3] = q1 * az - q2 * ay
    J[4] = q2 * ax - q0 * az
    J[5] = q0 * ay - q1 * ax
    return rz, ok, inv_z


def _lower_median(x: np.ndarray) -> float:
    """The lower of the two middle values for an even count, as ``torch.median``."""
    x = x.reshape(-1)
    k = (len(x) - 1) // 2
    return float(np.partition(x, k)[k])
