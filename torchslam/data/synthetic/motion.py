"""The analytic camera trajectories of the synthetic sequences and their exact kinematics.

Each trajectory is a smooth function of time built from differentiable torch operations, so
velocity, acceleration and angular rate follow by automatic differentiation (the IMU is
simulated from them).

Convention:
    World frame: z up; poses are camera-to-world, camera frame x right, y down, z forward.
"""

from __future__ import annotations

import enum
import math
from typing import Callable

import torch
from torch import Tensor

from ...errors import check_shape, parse_choice
from ...geometry import so3_exp, vex
from ...imu import Kinematics, time_derivatives
from .scene import _generator, _sub_seed

__all__ = ["SYNTHETIC_TRAJECTORIES", "SyntheticTrajectory", "trajectory_kinematics", "trajectory_pose"]


class SyntheticTrajectory(enum.StrEnum):
    """The camera motions of the synthetic sequences (``SyntheticConfig.trajectory``)."""

    ORBIT = "orbit"
    """Circles the room centre looking outward, a full turn per period: rotation-dominant."""
    TRANSLATE = "translate"
    """Slides sideways in front of a wall with little rotation: translation-dominant."""
    LOOP = "loop"
    """An ellipse through the room that returns to its start every period: for loop closure."""
    HANDHELD = "handheld"
    """A slow pan with hand-held shake."""


SYNTHETIC_TRAJECTORIES = tuple(k.value for k in SyntheticTrajectory)


def _normalize(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _look_at(p: Tensor, target: Tensor) -> Tensor:
    """(M, 3, 3) camera-to-world rotations looking from ``p`` at ``target`` with no roll (z up)."""
    z = _normalize(target - p)
    # x = normalize(z x e_z) written out, so no constant tensor enters the autodiff graph.
    x = _normalize(torch.stack([z[..., 1], -z[..., 0], torch.zeros_like(z[..., 0])], dim=-1))
    y = torch.linalg.cross(z, x)  # points down in the image
    return torch.stack([x, y, z], dim=-1)


def _shake(gen: torch.Generator, count: int, amplitude: float) -> tuple[Tensor, Tensor, Tensor]:
    """Random sinusoids (freq (3, n) Hz, amp (3, n), phase (3, n)) with a 1/f spectrum and ~``amplitude`` RMS."""
    f64 = torch.float64
    freq = 0.2 + 2.8 * torch.rand(3, count, generator=gen, dtype=f64)
    amp = 1.0 / freq
    amp = amp * (amplitude * math.sqrt(2.0) / amp.pow(2).sum(-1, keepdim=True).sqrt())
    phase = 2 * math.pi * torch.rand(3, count, generator=gen, dtype=f64)
    return freq, amp, phase


def _sinusoids(t: Tensor, params: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    freq, amp, phase = params
    return (amp * torch.sin(2 * math.pi * freq * t[:, None, None] + phase)).sum(-1)  # (M, 3)


def trajectory_pose(kind: SyntheticTrajectory | str, period: float, seed: int) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """Return the analytic camera motion ``kind`` as a function of time.

    The function maps (M,) float64 times (seconds) to ``R_wc`` (M, 3, 3) and camera centres
    (M, 3) in metres; it is smooth and built from differentiable torch operations, so velocities
    and accelerations follow by automatic differentiation.

    Args:
        kind: the trajectory.
        period: duration of one cycle, seconds.
        seed: the sequence seed (the hand-held shake is drawn from it).
    """
    kind, period = parse_choice(SyntheticTrajectory, kind, "trajectory"), float(period)
    gen = _generator(_sub_seed(seed, 2))
    shake_t, shake_r = _shake(gen, 8, 0.012), _shake(gen, 8, 0.008)

    def pose(t: Tensor) -> tuple[Tensor, Tensor]:
        th = 2 * math.pi * t / period
        s, c = torch.sin(th), torch.cos(th)
        if kind is SyntheticTrajectory.ORBIT:
            p = torch.stack([0.6 * c, 0.6 * s, 1.4 + 0.1 * torch.sin(2 * th)], -1)
            look = torch.stack([torch.cos(th + 0.3), torch.sin(th + 0.3), -0.25 + 0.1 * torch.sin(3 * th)], -1)
            return _look_at(p, p + look), p
        if kind is SyntheticTrajectory.TRANSLATE:
            p = torch.stack([1.0 * s, -1.2 + 0.15 * torch.sin(2 * th), 1.3 + 0.2 * torch.sin(2 * th + 1.0)], -1)
            look = torch.stack([0.1 * s, -torch.ones_like(s), -0.35 + 0.05 * c], -1)
            return _look_at(p, p + look), p
        if kind is SyntheticTrajectory.LOOP:
            p = torch.stack([1.5 * c, 1.1 * s, 1.35 + 0.1 * torch.sin(2 * th)], -1)
            target = torch.stack([3.0 * torch.cos(th + 0.8), 3.0 * torch.sin(th + 0.8), torch.full_like(th, 1.0)], -1)
            return _look_at(p, target), p
        # handheld: a slow pan from a standing position with hand shake in position and rotation.
        psi = 0.5 * s
        p = torch.stack([0.4 + 0.3 * s, 0.6 + 0.15 * torch.sin(2 * th), 1.5 + 0.05 * torch.sin(3 * th)], -1)
        look = torch.stack([torch.sin(psi), torch.cos(psi), torch.full_like(psi, -0.3)], -1)
        R = _look_at(p, p + look) @ so3_exp(_sinusoids(t, shake_r))
        return R, p + _sinusoids(t, shake_t)

    return pose


def trajectory_kinematics(pose: Callable[[Tensor], tuple[Tensor, Tensor]], times: Tensor) -> Kinematics:
    """Exact motion of the camera (= IMU) moving along ``pose`` (``trajectory_pose``) at ``times``.

    Acceleration and the rotation derivative come from automatic differentiation of the
    analytic trajectory (:func:`torchslam.imu.time_derivatives`; each sample depends only on its
    own time), so ``omega_b = vex(R^T dR/dt)`` is exact.

    Args:
        pose: the trajectory, a function of (M,) float64 times.
        times: (M,) float64 seconds.

    Returns:
        Kinematics with world acceleration and body angular rate.
    """
    check_shape(times, "M", "times")
    t = times.to(torch.float64)
    _, _, accel = time_derivatives(lambda x: pose(x)[1], t, 2)
    R, R_dot = time_derivatives(lambda x: pose(x)[0], t, 1)
    omega = vex(R.transpose(-1, -2) @ R_dot)
    return Kinematics(t, R, omega, accel)
