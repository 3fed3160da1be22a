"""The attitude filter's tilt correction run again online, its accelerometer corrected by the
camera's own acceleration (beyond the NI-SLAM paper).

``ahrs_attitude`` corrects roll and pitch by low-passing the accelerometer's direction, which is
gravity's only where the body does not accelerate. The body's own acceleration leaks into that
low-pass: attenuated by ``1 / sqrt(1 + (w tau)^2)`` at angular frequency ``w``, but on motion with
periods of a few seconds it still tilts the attitude by up to a degree (synthetic sequences,
noiseless IMU: 0.35-1.27 degrees at tau = 10 s), and an attitude error tilts every translation
NI-SLAM measures in its orthographic images. A visual-inertial system knows that acceleration:
it is the second derivative of the positions it tracks. ``AccelerationCompensation`` runs the
same low-pass (the same gains, gate and samples as the stream's filter) over
``R0 G_i f_i - a_w(t_i)`` instead of ``R0 G_i f_i``, with ``a_w`` from a quadratic fitted to the
tracked positions, and corrects each frame's attitude by the change in the tilt correction.

The fit over ``2 h + 1`` frames is centred, so the low-pass runs ``h + 1`` frames behind the
newest frame, and a frame's correction is the low-pass's state there: against a time constant
``tau`` of 10 s, a lag of a fraction of a second. Before the first window is full the samples up
to each frame go in uncorrected, as in the stream's own filter; after a discontinuity of the
tracked positions (``restart``) the state holds until a new window fills, and the samples in
between are then corrected by its first fit. A loop closure moves the keyframes without such a
discontinuity: the window takes the re-posed positions of its frames (``reposition``) and goes on.
Cost per frame: one 3-parameter least-squares fit and the stream's low-pass (``_linear_recurrence``)
over the few IMU samples since the previous frame, float64 on the host: about 0.5 ms.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError, ShapeError
from .attitude import AttitudeStream, _linear_recurrence, _swing_to, quat_xyzw_to_rotmat

__all__ = ["AccelerationCompensation"]

F64 = torch.float64


class AccelerationCompensation:
    """Attitude corrections from the tilt filter run with the tracked camera's acceleration removed.

    Call :meth:`observe` with every tracked position (stream time, stream world), :meth:`restart`
    where the positions jump (the world moved under them), and :meth:`correction` for a frame's
    attitude: ``C @ R_wc`` is its corrected attitude.

    Args:
        stream: an attitude stream the filter made (``AttitudeStream.tilt`` not None).
        half_window: ``h``: the acceleration at a frame comes from a quadratic fitted to the
            positions of the ``2 h + 1`` frames centred on it (h >= 2).
    """

    def __init__(self, stream: AttitudeStream, half_window: int = 5) -> None:
        if stream.tilt is None:
            raise ConfigError(f"stream: a {stream.source!r} stream has no attitude filter to run again")
        if not (isinstance(half_window, int) and half_window >= 2):
            raise ConfigError(f"half_window: expected an int >= 2 (a quadratic needs 5 frames), got {half_window!r}")
        tilt = stream.tilt
        self.h = half_window
        self.t = stream.timestamps.detach().cpu().numpy()  # the sample search runs in NumPy
        self.f = tilt.specific_force.detach().to("cpu", F64)
        self.alpha = tilt.alpha.detach().to("cpu", F64)
        self.up = tilt.up.detach().to("cpu", F64)
        self.g = tilt.gravity
        self.gate = tilt.accel_gate
        self.Q = tilt.to_filter.detach().to("cpu", F64)
        self._e_up = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        self._times: list[float] = []
        self._positions: list[Tensor] = []
        self._y: Tensor | None = None  # low-pass state after sample self._done
        self._done = -1
        self._last_accel: tuple[float, Tensor] | None = None  # (time, filter-world acceleration)
        self.compensated_samples = 0  # IMU samples run through the corrected low-pass
        self.max_correction_deg = 0.0  # largest correction handed out by ``correction``

    def _sample_before(self, t: float) -> int:
        """Index of the last sample at or before ``t`` (the first where none is)."""
        return int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1))

    def _start(self, t: float) -> None:
        k = self._sample_before(t)
        self._y, self._done = self.up[k], k

    def restart(self) -> None:
        """Forget the positions so far (they moved): the next window starts with the next one."""
        self._times.clear()
        self._positions.clear()
        self._last_accel = None

    @property
    def held(self) -> int:
        """How many of the newest observed positions the window holds (at most ``2 h + 1``)."""
        return len(self._times)

    def reposition(self, positions: Tensor | np.ndarray) -> None:
        """Replace the held positions by the same frames' new ones, (``held``, 3), oldest first.

        Where the world moves under the tracked frames (a loop closure re-poses their keyframes,
        each frame staying where it was relative to its keyframe), the window goes on with the
        moved positions instead of starting again (``restart``): with a loop closed every few
        keyframes, a window of ``2 h + 1`` frames would rarely fill, and the tilt correction
        would run on uncompensated samples.

        Raises:
            ShapeError: for another number of positions than ``held``.
        """
        p = torch.as_tensor(positions).detach().to("cpu", F64)
        if p.shape != (len(self._positions), 3):
            raise ShapeError(f"positions: expected ({len(self._positions)}, 3), the held frames, got {tuple(p.shape)}")
        self._positions = list(p.unbind(0))

    def observe(self, t: float, position: Tensor | np.ndarray) -> None:
        """Add the tracked position (3,) of a frame at stream time ``t``; advance the low-pass
        where a window of ``2 h + 1`` positions is complete."""
        if self._y is None:
            self._start(t)
        if self._times and not t > self._times[-1]:
            self.restart()  # not a forward step of time: start again rather than fit across it
        self._times.append(float(t))
        self._positions.append(torch.as_tensor(position).detach().to("cpu", F64).reshape(3))
        n = 2 * self.h + 1
        if len(self._times) < n:
            return
        if len(self._times) > n:
            del self._times[0], self._positions[0]
        tc = self._times[self.h]
        tau = np.asarray(self._times) - tc
        A = np.stack([np.ones_like(tau), tau, tau * tau], axis=1)
        # NumPy's least squares: torch's (MKL) gave run-to-run bit differences, which the
        # trajectory-equality tests of frames prepared ahead caught.
        coef, *_ = np.linalg.lstsq(A, torch.stack(self._positions).numpy(), rcond=None)
        self._advance(tc, self.Q @ torch.from_numpy(2.0 * coef[2]))

    def _run(self, lo: int, stop: int, accel: Tensor) -> Tensor:
        """The low-pass state after samples ``lo .. stop - 1`` from the current state, the
        acceleration (filter world) per sample (n, 3) or held (3,): the stream's recurrence."""
        w = self.f[lo:stop] - accel
        norm = w.norm(dim=1)
        alpha = torch.where((norm - self.g).abs() <= self.gate, self.alpha[lo:stop], 0.0)
        return _linear_recurrence(1 - alpha, alpha[:, None] * (w / norm.clamp_min(1e-12)[:, None]), self._y)[-1]

    def _advance(self, t_end: float, accel: Tensor) -> None:
        """Run the low-pass over the samples after ``self._done`` up to ``t_end`` with the
        acceleration interpolated from the previous fit (or held at ``accel`` for a first fit)."""
        stop = int(np.searchsorted(self.t, t_end, side="right"))
        lo = self._done + 1
        if stop > lo:
            if self._last_accel is None:
                a = accel
            else:
                t0, a0 = self._last_accel
                s = ((torch.from_numpy(self.t[lo:stop]) - t0) / max(t_end - t0, 1e-12)).clamp(0.0, 1.0)[:, None]
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
        k = self._sample_before(t)
        y = self._y
        if self._last_accel is None and k > self._done:
            # No acceleration known yet (the first frames, or since a restart): the samples up
            # to the frame go in uncorrected, as in the stream's own filter. Once one is known,
            # the state stays at the last fit's centre: running it on with that acceleration
            # held made each frame's correction jitter (hand-held shake changes the acceleration
            # faster than the fit follows).
            y = self._run(self._done + 1, k + 1, torch.zeros(3, dtype=F64))
        u = torch.stack([y, self.up[k]])
        u = u / u.norm(dim=1, keepdim=True).clamp_min(1e-12)
        L_new, L_old = quat_xyzw_to_rotmat(_swing_to(u, self._e_up))  # the corrections, filter world
        angle = math.degrees(math.acos(float((u[0] @ u[1]).clamp(-1.0, 1.0))))
        self.max_correction_deg = max(self.max_correction_deg, angle)
        return self.Q.T @ (L_new @ L_old.T) @ self.Q
