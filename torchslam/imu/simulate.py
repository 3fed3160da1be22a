"""IMU records and IMU simulation from ground-truth motion.

A gyroscope and an accelerometer are simulated from the true motion of the body (IMU) frame
with white noise and a random-walk bias on each axis, the usual continuous-time MEMS model:

    gyro_i  = omega_b(t_i) + b_g(t_i) + n_g,i
    accel_i = R_wb(t_i)^T (a_w(t_i) - g_w) + b_a(t_i) + n_a,i

``omega_b`` is the body angular velocity in the body frame (``R_wb^T dR_wb/dt = [omega_b]x``),
``a_w`` the world-frame acceleration of the body origin and ``g_w`` the gravity vector, so a
body at rest measures ``-R_wb^T g_w`` (the "up" direction, magnitude g).

Noise model:
    Densities are continuous-time and discretised at the sample spacing ``dt``: white noise has
    a per-sample standard deviation ``density / sqrt(dt)``; a bias random walk adds a step of
    standard deviation ``walk * sqrt(dt)`` per sample. Units: gyro noise density rad/s/sqrt(Hz),
    gyro bias walk rad/s^2/sqrt(Hz), accelerometer noise density m/s^2/sqrt(Hz), accelerometer
    bias walk m/s^3/sqrt(Hz).

Convention:
    World frame: gravity is a world-frame vector, ``(0, 0, -9.81)`` by default (z up), which is
    the case for the synthetic room and for TUM RGB-D motion-capture ground truth. The IMU
    (body) frame is assumed equal to the camera frame (x right, y down, z forward) for the
    synthetic sequences and for attitude simulated from camera ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import NON_NEGATIVE, ConfigError, Limit, ShapeError, check_float, check_increasing, check_limits, check_shape
from ..geometry import quat_xyzw_slerp, quat_xyzw_to_rotmat, rotmat_to_quat_xyzw, so3_exp, so3_log, vex
from ..stamps import STAMP_TOLERANCE_S

__all__ = [
    "GRAVITY_W",
    "ImuData",
    "ImuNoise",
    "Kinematics",
    "SimulatedImu",
    "interpolate_rotations",
    "kinematics_from_trajectory",
    "make_generator",
    "simulate_imu",
    "time_derivatives",
]

# Standard gravity in a z-up world frame, m/s^2.
GRAVITY_W = (0.0, 0.0, -9.81)


@dataclass(frozen=True)
class ImuData:
    """A stream of IMU samples.

    Attributes:
        timestamps: (M,) float64 seconds, strictly increasing.
        gyro: (M, 3) float64 angular velocity in the body (IMU) frame, rad/s.
        accel: (M, 3) float64 specific force in the body frame, m/s^2 (``-R_wb^T g_w`` at rest).
    """

    timestamps: Tensor
    gyro: Tensor
    accel: Tensor

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape(self.timestamps, "M", "timestamps", dims)
        check_shape(self.gyro, "M 3", "gyro", dims)
        check_shape(self.accel, "M 3", "accel", dims)
        for name in ("timestamps", "gyro", "accel"):
            if getattr(self, name).dtype != torch.float64:
                raise ShapeError(f"{name}: expected float64, got {getattr(self, name).dtype}")
        check_increasing(self.timestamps, "timestamps")

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    def slice(self, index) -> "ImuData":
        """Return the samples selected by ``index`` (slice, bool mask or increasing index tensor)."""
        return ImuData(self.timestamps[index], self.gyro[index], self.accel[index])


@dataclass(frozen=True)
class ImuNoise:
    """Noise of a simulated IMU (defaults: a good MEMS unit, the ADIS16448 class).

    Attributes:
        gyro_noise_density: gyroscope white noise, rad/s/sqrt(Hz).
        gyro_bias_walk: gyroscope bias random walk, rad/s^2/sqrt(Hz).
        accel_noise_density: accelerometer white noise, m/s^2/sqrt(Hz).
        accel_bias_walk: accelerometer bias random walk, m/s^3/sqrt(Hz).
        gyro_bias_init: standard deviation of the gyroscope bias at the first sample, rad/s
            (the residual after a start-up calibration).
        accel_bias_init: standard deviation of the accelerometer bias at the first sample, m/s^2.
    """

    gyro_noise_density: float = 1.7e-4
    gyro_bias_walk: float = 2.0e-5
    accel_noise_density: float = 2.0e-3
    accel_bias_walk: float = 3.0e-3
    gyro_bias_init: float = 5.0e-4
    accel_bias_init: float = 2.0e-2

    LIMITS: ClassVar[dict[str, Limit]] = {
        "gyro_noise_density": NON_NEGATIVE, "gyro_bias_walk": NON_NEGATIVE, "accel_noise_density": NON_NEGATIVE,
        "accel_bias_walk": NON_NEGATIVE, "gyro_bias_init": NON_NEGATIVE, "accel_bias_init": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        check_limits(self)

    @classmethod
    def noiseless(cls) -> "ImuNoise":
        """Return a model with every noise and bias term zero."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Kinematics:
    """True motion of the body frame sampled at IMU times.

    Attributes:
        timestamps: (M,) float64 seconds, strictly increasing.
        R_wb: (M, 3, 3) float64 body-to-world rotations.
        omega_b: (M, 3) float64 body angular velocity in the body frame, rad/s.
        accel_w: (M, 3) float64 acceleration of the body origin in the world frame, m/s^2.
    """

    timestamps: Tensor
    R_wb: Tensor
    omega_b: Tensor
    accel_w: Tensor

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape(self.timestamps, "M", "timestamps", dims)
        check_shape(self.R_wb, "M 3 3", "R_wb", dims)
        check_shape(self.omega_b, "M 3", "omega_b", dims)
        check_shape(self.accel_w, "M 3", "accel_w", dims)
        if self.timestamps.dtype != torch.float64:
            raise ShapeError(f"timestamps: expected float64, got {self.timestamps.dtype}")
        check_increasing(self.timestamps, "timestamps")


@dataclass(frozen=True)
class SimulatedImu:
    """A simulated IMU stream with the biases that corrupted it.

    Attributes:
        imu: the measurements.
        gyro_bias: (M, 3) float64 true gyroscope bias at each sample, rad/s.
        accel_bias: (M, 3) float64 true accelerometer bias at each sample, m/s^2.
    """

    imu: ImuData
    gyro_bias: Tensor
    accel_bias: Tensor


def make_generator(seed: int | torch.Generator, device: torch.device | str | None = None) -> torch.Generator:
    """Return ``seed`` if it is a generator, else a new CPU (or ``device``) generator seeded with it."""
    if isinstance(seed, torch.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"seed: expected an int or a torch.Generator, got {type(seed).__name__}")
    gen = torch.Generator(device=device if device is not None else "cpu")
    gen.manual_seed(int(seed) % (2**63))
    return gen


def interpolate_rotations(
    timestamps: Tensor, R: Tensor, times: Tensor, max_gap: float = math.inf, quats: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Interpolate rotations at ``times`` by SLERP between the bracketing samples.

    Args:
        timestamps: (N,) float64 sample times, strictly increasing, seconds.
        R: (N, 3, 3) rotations at the sample times.
        times: (M,) float64 query times, seconds.
        max_gap: queries whose bracketing samples are further apart than this, or that lie
            outside ``[timestamps[0], timestamps[-1]]``, are invalid.
        quats: (N, 4) ``rotmat_to_quat_xyzw(R)`` where the caller keeps it (an attitude stream
            queried every frame); otherwise only the bracketing samples are converted.

    Returns:
        R_interp: (M, 3, 3) rotations, in ``R``'s dtype (identity where invalid).
        valid: (M,) bool.
    """
    dims: dict[str, int] = {}
    check_shape(timestamps, "N", "timestamps", dims)
    check_shape(R, "N 3 3", "R", dims)
    check_shape(times, "M", "times")
    check_float(R, "R")
    if times.dtype != torch.float64 or timestamps.dtype != torch.float64:
        raise ShapeError(f"times: expected float64 timestamps, got {times.dtype} and {timestamps.dtype}")
    n, m = timestamps.shape[0], times.shape[0]
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    if n == 0:
        return eye.expand(m, 3, 3).clone(), torch.zeros(m, dtype=torch.bool, device=times.device)
    hi = torch.searchsorted(timestamps, times).clamp(1, max(n - 1, 1))
    lo = hi - 1
    if n == 1:
        hi = lo = torch.zeros_like(hi)
    t0, t1 = timestamps[lo], timestamps[hi]
    span = t1 - t0
    alpha = torch.where(span > 0, (times - t0) / torch.where(span > 0, span, torch.ones_like(span)), torch.zeros_like(span))
    # Slack for round-off, so a stream sampled exactly every max_gap seconds is not rejected.
    valid = (times >= timestamps[0]) & (times <= timestamps[-1]) & (span <= max_gap + STAMP_TOLERANCE_S)
    # Only the bracketing samples are converted (the quaternion of each rotation does not depend
    # on the others, so this equals indexing ``quats``): the stream is queried every frame.
    q = rotmat_to_quat_xyzw(torch.cat([R[lo], R[hi]])) if quats is None else torch.cat([quats[lo], quats[hi]])  # (2M, 4)
    Ri = quat_xyzw_to_rotmat(quat_xyzw_slerp(q[:m], q[m:], alpha.to(R.dtype)))
    return torch.where(valid[:, None, None], Ri, eye), valid


def _grid(t_start: float, t_end: float, rate: float, like: Tensor) -> Tensor:
    """Uniform times spanning exactly [t_start, t_end] with spacing as close to 1 / rate as fits."""
    steps = max(1, int(round((t_end - t_start) * rate)))
    return torch.linspace(t_start, t_end, steps + 1, dtype=torch.float64, device=like.device)


def time_derivatives(fn: Callable[[Tensor], Tensor], times: Tensor, order: int) -> list[Tensor]:
    """Evaluate a per-sample function of time and its exact time derivatives by autograd.

    ``fn`` must map (M,) times to (M, ...) values with row i depending on ``times[i]`` only;
    then the gradient of a column's sum is that column's derivative at every sample, so
    ``order`` rounds of reverse-mode differentiation give exact derivatives.

    Args:
        fn: the function, built from differentiable torch operations.
        times: (M,) float64 seconds.
        order: highest derivative wanted (>= 1).

    Returns:
        ``[fn(t), fn'(t), ..., fn^(order)(t)]``, each (M, ...) and detached.
    """
    with torch.enable_grad():
        x = times.detach().clone().requires_grad_(True)
        out = [fn(x)]
        for k in range(order):
            y = out[-1]
            flat = y.reshape(y.shape[0], -1)
            cols = []
            for j in range(flat.shape[1]):
                g = torch.autograd.grad(flat[:, j].sum(), x, create_graph=k < order - 1, retain_graph=True, allow_unused=True)[0]
                cols.append(torch.zeros_like(x) if g is None else g)
            out.append(torch.stack(cols, dim=-1).reshape(y.shape))
    return [o.detach() for o in out]


def _hermite_rotations(timestamps: Tensor, R: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """Rotations (M, 3, 3) and body rates (M, 3) of the C1 Hermite curve through ``R`` at ``t``."""
    dt = timestamps[1:] - timestamps[:-1]  # (N-1,)
    phi = so3_log(R[:-1].transpose(-1, -2) @ R[1:])  # (N-1, 3) segment rotation vectors
    mean_rate = phi / dt[:, None]
    # Knot slopes: time-weighted average of the adjacent segments' mean rates.
    w_prev, w_next = dt[1:, None], dt[:-1, None]
    inner = (mean_rate[:-1] * w_prev + mean_rate[1:] * w_next) / (w_prev + w_next)
    slope = torch.cat([mean_rate[:1], inner, mean_rate[-1:]], dim=0)  # (N, 3)
    seg = (torch.searchsorted(timestamps, t, right=True) - 1).clamp(0, timestamps.shape[0] - 2)
    t0, d = timestamps[seg], dt[seg]
    m0, m1, ph, R0 = slope[seg] * d[:, None], slope[seg + 1] * d[:, None], phi[seg], R[seg]

    def curve(x: Tensor) -> Tensor:
        s = ((x - t0) / d)[:, None]
        s2, s3 = s * s, s * s * s
        h = (s3 - 2 * s2 + s) * m0 + (3 * s2 - 2 * s3) * ph + (s3 - s2) * m1
        return R0 @ so3_exp(h)

    R_t, R_dot = time_derivatives(curve, t, 1)
    return R_t, vex(R_t.transpose(-1, -2) @ R_dot)


def kinematics_from_trajectory(
    timestamps: Tensor, T_wb: Tensor, rate: float = 200.0, accel_smoothing: float = 0.05
) -> Kinematics:
    """Derive continuous body motion from discrete poses, sampled on a regular IMU grid.

    Rotation follows a C1 cubic Hermite curve through every pose: on segment k,
    ``R(t) = R_k Exp(h(s))`` with ``s = (t - t_k) / dt_k`` and ``h`` the cubic in the tangent space
    of ``R_k`` with ``h(0) = 0``, ``h(1) = log(R_k^T R_k+1)`` and end slopes from the neighbouring
    segments' mean rates. Its body rate ``vex(R^T dR/dt)`` (by automatic differentiation) is
    continuous, so a gyroscope sampling it can be integrated back to the poses (a piecewise-SLERP
    curve would have a rate that jumps at every pose, which no sampled gyroscope reproduces).
    Positions are linearly interpolated, smoothed with a Gaussian of standard deviation
    ``accel_smoothing`` seconds and differentiated twice: motion-capture positions are too
    jittery to differentiate raw, so the accelerometer's motion term is a smoothed estimate.

    Args:
        timestamps: (N,) float64 pose times, strictly increasing, N >= 2.
        T_wb: (N, 4, 4) body-to-world poses (for camera ground truth: ``T_wc``).
        rate: IMU sample rate, Hz.
        accel_smoothing: Gaussian smoothing of positions before differentiation, seconds (0: none).

    Returns:
        Kinematics on a uniform grid from ``timestamps[0]`` to ``timestamps[-1]`` inclusive whose
        spacing is the closest to ``1 / rate`` that divides the span.
    """
    dims: dict[str, int] = {}
    check_shape(timestamps, "N", "timestamps", dims)
    check_shape(T_wb, "N 4 4", "T_wb", dims)
    if timestamps.dtype != torch.float64:
        raise ShapeError(f"timestamps: expected float64, got {timestamps.dtype}")
    if timestamps.shape[0] < 2:
        raise ShapeError(f"timestamps: need at least 2 poses to derive motion, got {timestamps.shape[0]}")
    if not rate > 0:
        raise ConfigError(f"rate: expected a positive IMU rate in Hz, got {rate}")
    if not accel_smoothing >= 0:
        raise ConfigError(f"accel_smoothing: expected seconds >= 0, got {accel_smoothing}")
    T_wb = T_wb.to(torch.float64)
    t = _grid(float(timestamps[0]), float(timestamps[-1]), rate, timestamps)
    step = float(t[1] - t[0])
    R_wb, omega_b = _hermite_rotations(timestamps, T_wb[:, :3, :3], t)
    # Positions: linear interpolation on the grid, then a smoothed second difference.
    hi = torch.searchsorted(timestamps, t).clamp(1, timestamps.shape[0] - 1)
    lo = hi - 1
    alpha = ((t - timestamps[lo]) / (timestamps[hi] - timestamps[lo]))[:, None]
    p = T_wb[lo, :3, 3] + alpha * (T_wb[hi, :3, 3] - T_wb[lo, :3, 3])  # (M, 3)
    if accel_smoothing > 0 and t.shape[0] > 2:
        sigma = accel_smoothing / step  # samples
        half = int(math.ceil(4 * sigma))
        k = torch.arange(-half, half + 1, dtype=torch.float64, device=t.device)
        kernel = torch.exp(-0.5 * (k / sigma) ** 2)
        kernel = kernel / kernel.sum()
        padded = F.pad(p.T[None], (half, half), mode="replicate")  # (1, 3, M + 2 half)
        p = F.conv1d(padded.transpose(0, 1), kernel[None, None]).squeeze(1).T  # (M, 3)
    accel_w = torch.zeros_like(p)
    if t.shape[0] > 2:
        accel_w[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / (step * step)
        accel_w[0], accel_w[-1] = accel_w[1], accel_w[-2]
    return Kinematics(t, R_wb, omega_b, accel_w)


def simulate_imu(
    kinematics: Kinematics,
    noise: ImuNoise | None = None,
    gravity_w: Tensor | tuple[float, float, float] = GRAVITY_W,
    generator: torch.Generator | int = 0,
) -> SimulatedImu:
    """Simulate gyroscope and accelerometer samples from true motion.

    Args:
        kinematics: the true motion at the IMU sample times.
        noise: noise and bias model (default :class:`ImuNoise`); ``ImuNoise.noiseless()`` gives
            exact measurements.
        gravity_w: (3,) gravity vector in the world frame, m/s^2.
        generator: a ``torch.Generator`` or an int seed; draws are made in a fixed order, so the
            same seed gives the same stream.

    Returns:
        The measurements and the true biases, float64 on the kinematics' device.
    """
    noise = ImuNoise() if noise is None else noise
    t = kinematics.timestamps
    device = t.device
    g_w = torch.as_tensor(gravity_w, dtype=torch.float64, device=device)
    check_shape(g_w, "3", "gravity_w")
    gen = make_generator(generator, device)
    m = t.shape[0]
    if m > 1:
        dt = torch.diff(t)
        dt = torch.cat([dt, dt[-1:]])  # (M,): spacing to the next sample (last repeats)
    else:
        dt = torch.ones_like(t)
    sqrt_dt = dt.sqrt()[:, None]

    def draw(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float64, device=device)

    bg0, ba0 = draw(3) * noise.gyro_bias_init, draw(3) * noise.accel_bias_init
    walk_g, walk_a = draw(m, 3), draw(m, 3)
    white_g, white_a = draw(m, 3), draw(m, 3)
    # Bias at sample i has taken i random-walk steps (the step between samples k-1 and k uses dt[k-1]).
    steps_g = torch.cat([torch.zeros_like(walk_g[:1]), walk_g[1:] * noise.gyro_bias_walk * sqrt_dt[:-1]])
    steps_a = torch.cat([torch.zeros_like(walk_a[:1]), walk_a[1:] * noise.accel_bias_walk * sqrt_dt[:-1]])
    gyro_bias = bg0 + torch.cumsum(steps_g, dim=0)
    accel_bias = ba0 + torch.cumsum(steps_a, dim=0)
    R = kinematics.R_wb.to(torch.float64)
    specific_w = kinematics.accel_w.to(torch.float64) - g_w  # (M, 3)
    specific_b = (R.transpose(-1, -2) @ specific_w[:, :, None])[:, :, 0]
    gyro = kinematics.omega_b.to(torch.float64) + gyro_bias + white_g * (noise.gyro_noise_density / sqrt_dt)
    accel = specific_b + accel_bias + white_a * (noise.accel_noise_density / sqrt_dt)
    return SimulatedImu(ImuData(t.to(torch.float64), gyro, accel), gyro_bias, accel_bias)
