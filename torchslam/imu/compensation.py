"""The attitude filter's tilt correction run again online, its accelerometer corrected by the
camera's own acceleration (beyond the NI-SLAM paper).

``ahrs_attitude`` corrects roll and pitch by low-passing the accelerometer's direction, which is
gravity's only where the body does not accelerate. The body's own acceleration leaks into that
low-pass: attenuated by ``1 / sqrt(1 + (w tau)^2)`` at angular frequency ``w``, but on motion with
periods of a few seconds it still tilts the attitude by up to a degree (synthetic sequences,
noiseless IMU: 0.65-1.27 degrees at tau = 10 s), and an attitude error tilts every translation
NI-SLAM measures in its orthographic images. A visual-inertial system knows that acceleration:
it is the second derivative of the positions it tracks. ``AccelerationCompensation`` runs the
same low-pass (the same gains, gate and samples as the stream's filter) over
``R0 G_i f_i - a_w(t_i)`` instead of ``R0 G_i f_i``, with ``a_w`` from a quadratic fitted to the
tracked positions, and corrects each frame's attitude by the change in the tilt correction.

The fit over ``2 h + 1`` frames is centred, so the low-pass runs ``h + 1`` frames behind the
newest frame, and a frame's correction is the low-pass's state there: against a time constant
``tau`` of 10 s, a lag of a fraction of a second. Before the first window is full the samples up
to each frame go in uncorrected, as in the stream's own filter; after a discontinuity of the
tracked positions (a loop closure moves the keyframes) the state holds until a new window fills,
and the samples in between are then corrected by its first fit.
Cost per frame: one 3-parameter least-squares fit and a low-pass over the few IMU samples since
the previous frame (NumPy, float64), microseconds.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError
from .attitude import TiltInputs

__all__ = ["AccelerationCompensation"]

_UP = np.array([0.0, 0.0, 1.0])


def _swing(u: np.ndarray) -> np.ndarray:
    """(3, 3) smallest rotation taking the unit vector ``u`` onto +z (Rodrigues)."""
    axis = np.cross(u, _UP)
    s, c = float(np.linalg.norm(axis)), float(u @ _UP)
    if s < 1e-15:
        return np.eye(3)
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _low_pass(y0: np.ndarray, w: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(n, 3) states of ``y_i = (1 - a_i) y_{i-1} + a_i w_i`` from ``y0``, without a loop.

    ``y_i = P_i (y0 + sum_{j<=i} a_j w_j / P_j)`` with ``P_i = prod_{j<=i} (1 - a_j)``; the gains
    are below 1e-2 per sample, so ``P`` stays far from 0 over the few samples of a frame.
    """
    P = np.cumprod(1.0 - alpha)
    return P[:, None] * (y0 + np.cumsum((alpha / P)[:, None] * w, axis=0))


class AccelerationCompensation:
    """Attitude corrections from the tilt filter run with the tracked camera's acceleration removed.

    Call :meth:`observe` with every tracked position (stream time, stream world), :meth:`restart`
    where the positions jump (the world moved under them), and :meth:`correction` for a frame's
    attitude: ``C @ R_wc`` is its corrected attitude.

    Args:
        tilt: the stream's ``TiltInputs`` (``AttitudeStream.tilt``).
        half_window: ``h``: the acceleration at a frame comes from a quadratic fitted to the
            positions of the ``2 h + 1`` frames centred on it (h >= 2).
    """

    def __init__(self, tilt: TiltInputs, half_window: int = 5) -> None:
        if not (isinstance(half_window, int) and half_window >= 2):
            raise ConfigError(f"half_window: expected an int >= 2 (a quadratic needs 5 frames), got {half_window!r}")
        self.h = half_window
        self.t = tilt.timestamps.detach().cpu().numpy()
        self.f = tilt.specific_force.detach().cpu().numpy()
        self.alpha = tilt.alpha.detach().cpu().numpy()
        self.up = tilt.up.detach().cpu().numpy()
        self.g = tilt.gravity
        self.gate = tilt.accel_gate
        self.Q = tilt.to_filter.detach().cpu().numpy().astype(np.float64)
        self._times: list[float] = []
        self._positions: list[np.ndarray] = []
        self._y: np.ndarray | None = None  # low-pass state after sample self._done
        self._done = -1
        self._last_accel: tuple[float, np.ndarray] | None = None  # (time, filter-world acceleration)
        self.compensated_samples = 0  # IMU samples run through the corrected low-pass
        self.max_correction_deg = 0.0  # largest correction handed out by ``correction``

    def _start(self, t: float) -> None:
        k = int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1))
        self._y, self._done = self.up[k].copy(), k

    def restart(self) -> None:
        """Forget the positions so far (they moved): the next window starts with the next one."""
        self._times.clear()
        self._positions.clear()
        self._last_accel = None

    def observe(self, t: float, position: Tensor | np.ndarray) -> None:
        """Add the tracked position (3,) of a frame at stream time ``t``; advance the low-pass
        where a window of ``2 h + 1`` positions is complete."""
        if self._y is None:
            self._start(t)
        if self._times and not t > self._times[-1]:
            self.restart()  # not a forward step of time: start again rather than fit across it
        p = position.detach().cpu().numpy() if isinstance(position, Tensor) else np.asarray(position)
        self._times.append(float(t))
        self._positions.append(p.astype(np.float64).reshape(3))
        n = 2 * self.h + 1
        if len(self._times) < n:
            return
        if len(self._times) > n:
            del self._times[0], self._positions[0]
        tc = self._times[self.h]
        tau = np.asarray(self._times) - tc
        A = np.stack([np.ones_like(tau), tau, tau * tau], axis=1)
        coef, *_ = np.linalg.lstsq(A, np.stack(self._positions), rcond=None)
        accel = self.Q @ (2.0 * coef[2])
        self._advance(tc, accel)

    def _run(self, lo: int, stop: int, accel: np.ndarray) -> np.ndarray:
        """The low-pass state after samples ``lo .. stop - 1`` from the current state, the
        acceleration (filter world) per sample (n, 3) or held (3,)."""
        w = self.f[lo:stop] - accel
        norm = np.linalg.norm(w, axis=1)
        alpha = np.where(np.abs(norm - self.g) <= self.gate, self.alpha[lo:stop], 0.0)
        return _low_pass(self._y, w / np.maximum(norm, 1e-12)[:, None], alpha)[-1]

    def _advance(self, t_end: float, accel: np.ndarray) -> None:
        """Run the low-pass over the samples after ``self._done`` up to ``t_end`` with the
        acceleration interpolated from the previous fit (or held at ``accel`` for a first fit)."""
        stop = int(np.searchsorted(self.t, t_end, side="right"))
        lo = self._done + 1
        if stop > lo:
            if self._last_accel is None:
                a = accel
            else:
                t0, a0 = self._last_accel
                s = np.clip((self.t[lo:stop] - t0) / max(t_end - t0, 1e-12), 0.0, 1.0)[:, None]
                a = a0 + s * (accel - a0)
            self._y = self._run(lo, stop, a)
            self._done = stop - 1
            self.compensated_samples += stop - lo
        self._last_accel = (t_end, accel)

    def correction(self, t: float) -> Tensor:
        """(3, 3) float64 rotation ``C`` in the stream's world: ``C @ R_wc(t)`` is the attitude at
        stream time ``t`` with the compensated tilt correction instead of the stream's."""
        if self._y is None:
            self._start(t)
        stop = int(np.searchsorted(self.t, t, side="right"))
        k = int(np.clip(stop - 1, 0, len(self.t) - 1))
        y = self._y
        if self._last_accel is None and stop > self._done + 1:
            # No acceleration known yet (the first frames, or since a restart): the samples up
            # to the frame go in uncorrected, as in the stream's own filter. Once one is known,
            # the state stays at the last fit's centre: running it on with that acceleration
            # held made each frame's correction jitter (hand-held shake changes the acceleration
            # faster than the fit follows).
            y = self._run(self._done + 1, stop, np.zeros(3))
        u_old = self.up[k] / max(float(np.linalg.norm(self.up[k])), 1e-12)
        u_new = y / max(float(np.linalg.norm(y)), 1e-12)
        C = _swing(u_new) @ _swing(u_old).T  # in the filter's world
        angle = math.degrees(math.acos(float(np.clip(u_old @ u_new, -1.0, 1.0))))
        self.max_correction_deg = max(self.max_correction_deg, angle)
        return torch.from_numpy(self.Q.T @ C @ self.Q)
