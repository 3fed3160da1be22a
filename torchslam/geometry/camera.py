"""Pinhole camera: intrinsics, back-projection of depth images, projection, pyramid scaling.

Convention:
    Intrinsics as a tensor are ``(..., 4)`` = ``(fx, fy, cx, cy)`` in pixels, with pixel centres
    at integer coordinates (``u = fx x / z + cx``). Camera frame: x right, y down, z forward.

Lens distortion (optional, ``PinholeCamera.distortion``) is the Brown-Conrady model on normalised
coordinates ``(x, y) = (X / Z, Y / Z)`` with the coefficient order ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``
(the order OpenCV and the TUM RGB-D calibration use). With ``r^2 = x^2 + y^2``:
``x_d = x f(r) + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``y_d = y f(r) + p1 (r^2 + 2 y^2) + 2 p2 x y``,
``f(r) = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`` and the pixel is
``u = fx x_d + cx``, ``v = fy y_d + cy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cache import FifoCache
from ..devices import numpy_viewable
from ..errors import ConfigError, ShapeError, check_float, check_shape

__all__ = [
    "PinholeCamera",
    "backproject_depth",
    "distort_normalized",
    "distort_planes",
    "intrinsics_matrix",
    "project_points",
    "scale_intrinsics",
    "undistorted_rays",
]

_DISTORTION_LENGTHS = (0, 4, 5, 8)


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of one camera, its image size and optional lens distortion.

    Attributes:
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels (pixel centres at integers).
        width, height: image size, pixels.
        distortion: Brown-Conrady coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (0, 4, 5 or 8
            values, see the module docstring) acting on normalised coordinates, or None for an
            ideal pinhole. Stored as a tuple of floats.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"PinholeCamera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (self.width > 0 and self.height > 0):
            raise ConfigError(f"PinholeCamera: image size must be positive, got {self.width}x{self.height}")
        if self.distortion is not None:
            try:
                d = tuple(float(c) for c in self.distortion)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"PinholeCamera: distortion must be a sequence of numbers, got {self.distortion!r}") from exc
            if len(d) not in _DISTORTION_LENGTHS:
                raise ShapeError(
                    f"PinholeCamera: distortion must have 0, 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {len(d)}"
                )
            if not all(math.isfinite(c) for c in d):
                raise ConfigError(f"PinholeCamera: distortion coefficients must be finite, got {d}")
            object.__setattr__(self, "distortion", d)

    @property
    def has_distortion(self) -> bool:
        """True when ``distortion`` holds any non-zero coefficient."""
        return self.distortion is not None and any(c != 0.0 for c in self.distortion)

    def as_tensor(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """Return ``(4,)`` intrinsics ``(fx, fy, cx, cy)``."""
        return torch.tensor([self.fx, self.fy, self.cx, self.cy], dtype=dtype, device=device)

    def scaled(self, factor: float) -> "PinholeCamera":
        """Return the camera of an image resized by ``factor`` (e.g. 0.5 for one pyramid level)."""
        fx, fy, cx, cy = _scale(self.fx, self.fy, self.cx, self.cy, factor, factor)
        # Distortion acts on normalised coordinates, which resizing the image leaves unchanged.
        size = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        return PinholeCamera(fx, fy, cx, cy, *size, distortion=self.distortion)


def _scale(fx, fy, cx, cy, sx, sy):
    # Pixel centres sit at integers, so the continuous image edge is at -0.5: scale about it.
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5


def scale_intrinsics(intrinsics: Tensor, sx: float, sy: float | None = None) -> Tensor:
    """Scale ``(..., 4)`` intrinsics for an image resized by ``sx`` (and ``sy``, default ``sx``)."""
    check_shape(intrinsics, "... 4", "intrinsics")
    sy = sx if sy is None else sy
    fx, fy, cx, cy = intrinsics.unbind(-1)
    return torch.stack(_scale(fx, fy, cx, cy, sx, sy), dim=-1)


def intrinsics_matrix(intrinsics: Tensor) -> Tensor:
    """Return ``(..., 3, 3)`` calibration matrices K from ``(..., 4)`` intrinsics."""
    check_shape(intrinsics, "... 4", "intrinsics")
    fx, fy, cx, cy = intrinsics.unbind(-1)
    o, one = torch.zeros_like(fx), torch.ones_like(fx)
    return torch.stack([fx, o, cx, o, fy, cy, o, o, one], -1).reshape(intrinsics.shape[:-1] + (3, 3))


def _distortion_terms(d: tuple[float, ...]) -> tuple[float, ...]:
    """The 8 coefficients ``k1 k2 p1 p2 k3 k4 k5 k6`` with the missing ones zero."""
    return tuple(d) + (0.0,) * (8 - len(d))


def distort_normalized(xy: Tensor, distortion: tuple[float, ...] | None) -> Tensor:
    """Apply the forward Brown-Conrady model to normalised coordinates (module docstring).

    Args:
        xy: (..., 2) ideal normalised coordinates ``(X / Z, Y / Z)``.
        distortion: coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` or None (returns ``xy``).

    Returns:
        (..., 2) distorted normalised coordinates; pixels are ``fx x_d + cx``, ``fy y_d + cy``.
    """
    check_shape(xy, "... 2", "xy")
    check_float(xy, "xy")
    if distortion is None or len(distortion) == 0:
        return xy
    if len(distortion) not in _DISTORTION_LENGTHS:
        raise ShapeError(f"distortion: expected 0, 4, 5 or 8 coefficients, got {len(distortion)}")
    x, y = xy.unbind(-1)
    return torch.stack(distort_planes(x, y, distortion), dim=-1)


def distort_planes(x: Tensor, y: Tensor, distortion: tuple[float, ...]) -> tuple[Tensor, Tensor]:
    """``distort_normalized`` on separate coordinate tensors (the same arithmetic, bit for bit).

    Callers that hold the coordinates as planes (e.g. ``(B, 2, N)``) avoid interleaving them
    into ``(..., 2)`` and back, which over a 640x480 image costs more than the model itself.
    Inputs are trusted (``distort_normalized`` validates).

    Args:
        x: (...) ideal normalised ``X / Z``.
        y: (...) ideal normalised ``Y / Z``, same shape.
        distortion: coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``.

    Returns:
        ``(x_d, y_d)`` distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = _distortion_terms(distortion)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if k4 or k5 or k6:
        radial = radial / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2
    return xd, yd


def distort_planes_with_jacobian(x, y, distortion: tuple[float, ...]):
    """``distort_planes`` and its derivative at once, on coordinate planes (tensors or arrays).

    Returns ``(x_d, y_d, j00, j01, j10, j11)``, the ``j`` as ``_jacobian_planes`` (``d x_d / dx``,
    ``d x_d / dy``, ``d y_d / dx``, ``d y_d / dy``). For the five-coefficient model (``k4 = k5 =
    k6 = 0``, TUM's and OpenCV's default) the two share their terms (about half the operations of
    calling both; the same values to round-off, tested); the rational model calls both.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = _distortion_terms(distortion)
    if k4 or k5 or k6:
        xd, yd = distort_planes(x, y, distortion)
        return (xd, yd, *_jacobian_planes(x, y, distortion))
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad2 = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # 2 d radial / d r2
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * xx)
    yd = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy
    j01 = xy * drad2 + 2 * (p1 * x + p2 * y)
    j00 = radial + xx * drad2 + 2 * p1 * y + 6 * p2 * x
    j11 = radial + yy * drad2 + 6 * p1 * y + 2 * p2 * x
    return xd, yd, j00, j01, j01, j11


_RAYS_CACHE: FifoCache[Tensor] = FifoCache(8)


def undistorted_rays(
    camera: PinholeCamera, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None, step: int = 1
) -> Tensor:
    """Normalised viewing rays ``(x, y) = (X / Z, Y / Z)`` of every pixel, lens distortion removed.

    Pixel ``(u, v)`` (row-major, ``u`` the column) shows the point whose ideal normalised
    coordinates ``(x, y)`` distort (``distort_normalized``) to ``((u - cx) / fx, (v - cy) / fy)``.
    The inversion starts from OpenCV's iterative ``undistortPoints`` and is finished with
    Newton steps on the forward model in float64 (analytic 2x2 Jacobian), so that re-distorting
    the rays reproduces the pixel grid to well below 1e-6 px over the TUM fr1/fr2 images. Without
    distortion the rays are exactly ``((u - cx) / fx, (v - cy) / fy)`` as ``backproject_depth``
    computes them.

    The float64 rays of a distorted camera are kept in a small cache (the inversion costs about
    0.25 s for 640x480 on a CPU core), so runs on the same camera compute them once.

    Args:
        camera: intrinsics, image size and distortion.
        dtype: floating dtype of the result.
        device: device of the result.
        step: rays of every ``step``-th pixel in x and y only (the pixels ``(k step, l step)``),
            the rows and columns ``[::step, ::step]`` of the full result, computed alone.

    Returns:
        (H*W, 2) normalised coordinates, row-major pixel order (``backproject_depth``'s order);
        with ``step``, (ceil(H/step) * ceil(W/step), 2).

    Raises:
        ConfigError: when the inversion does not converge (distortion too strong for the image,
            i.e. the forward model folds over inside the field of view).
    """
    if not isinstance(camera, PinholeCamera):
        raise ShapeError(f"camera: expected a PinholeCamera, got {type(camera).__name__}")
    if not (isinstance(step, int) and step >= 1):
        raise ConfigError(f"step: expected a positive integer, got {step!r}")
    if not camera.has_distortion:
        return _pinhole_rays(camera, dtype, device, step)
    xy = _RAYS_CACHE.get_or_compute((camera, step), lambda: _invert_distortion(camera, step))
    return xy.to(dtype=dtype, device=device, copy=True)


def undistort_pixels(uv: Tensor, camera: PinholeCamera, newton_steps: int = 8) -> Tensor:
    """Ideal normalised rays (K, 2) float64 of pixels ``uv`` (K, 2) through the lens model.

    OpenCV's iterative ``undistortPoints`` gives the start; ``newton_steps`` Newton steps on the
    forward model (``distort_normalized``, analytic 2x2 Jacobian, closed-form solve) finish it to
    float64 precision. Where the Jacobian is singular (a fold of the model) the step is skipped.
    """
    uv = uv.to(torch.float64)
    xd = torch.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], -1)
    if uv.shape[0] == 0 or not camera.has_distortion:
        return xd
    import cv2  # only distorted cameras need OpenCV; keep it out of the geometry import

    K = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    d = np.asarray(camera.distortion, dtype=np.float64)
    pixels = uv.cpu().numpy().reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4: the iterative inversion has its own name
        start = cv2.undistortPointsIter(pixels, K, d, None, None, criteria)
    else:  # OpenCV 5: undistortPoints takes the termination criteria
        start = cv2.undistortPoints(pixels, K, d, None, None, None, criteria)
    xy = torch.from_numpy(np.ascontiguousarray(start.reshape(-1, 2), dtype=np.float64)).to(uv.device)
    if numpy_viewable(xy) and numpy_viewable(xd):
        out = xy.numpy().copy()
        for c in range(0, len(out), _NEWTON_CHUNK):  # a chunk's temporaries stay in cache
            part = out[c : c + _NEWTON_CHUNK]
            part[:, 0], part[:, 1] = _newton_numpy(part[:, 0], part[:, 1], xd.numpy()[c : c + _NEWTON_CHUNK], camera.distortion, newton_steps)
        return torch.from_numpy(out)
    return _newton_torch(xy, xd, camera.distortion, newton_steps)


def _newton_torch(xy: Tensor, xd: Tensor, distortion: tuple[float, ...], steps: int) -> Tensor:
    """``steps`` Newton steps from ``xy`` (K, 2) towards the rays that distort to ``xd`` (K, 2)."""
    for _ in range(steps):
        res = distort_normalized(xy, distortion) - xd
        J = _distortion_jacobian(xy, distortion)  # (K, 2, 2)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, math.inf))  # a fold: no step
        step = torch.stack(
            [J[:, 1, 1] * res[:, 0] - J[:, 0, 1] * res[:, 1], J[:, 0, 0] * res[:, 1] - J[:, 1, 0] * res[:, 0]], dim=-1
        )
        xy = xy - step / det[:, None]
    return xy


_NEWTON_CHUNK = 8192  # points per chunk of undistort_pixels' NumPy Newton steps


def _newton_numpy(x: np.ndarray, y: np.ndarray, xd: np.ndarray, distortion: tuple[float, ...], steps: int):
    """``undistort_pixels``' Newton steps in NumPy on coordinate planes: the torch steps'
    model and Jacobian (``distort_planes``, ``_jacobian_planes``, plain arithmetic that runs on
    arrays as on tensors), so the same bits; over the 307,200 pixels of a 640x480 camera the
    torch version's interleaving of planes into (K, 2) and (K, 2, 2) tensors cost most of the
    0.6 s that a run's start spent on its camera's rays."""
    tx, ty = xd[:, 0], xd[:, 1]
    for _ in range(steps):
        xm, ym = distort_planes(x, y, distortion)
        res0, res1 = xm - tx, ym - ty
        j00, j01, j10, j11 = _jacobian_planes(x, y, distortion)
        det = j00 * j11 - j01 * j10
        det = np.where(np.abs(det) > 1e-12, det, math.inf)  # a fold: no step
        x = x - (j11 * res0 - j01 * res1) / det
        y = y - (j00 * res1 - j10 * res0) / det
    return x, y


def _invert_distortion(camera: PinholeCamera, step: int) -> Tensor:
    """float64 CPU (N, 2) undistorted rays of the pixels ``[::step, ::step]`` (``undistorted_rays``)."""
    xd = _pinhole_rays(camera, torch.float64, "cpu", step)  # distorted normalised coordinates of the pixels
    v, u = torch.meshgrid(
        torch.arange(0, camera.height, step, dtype=torch.float64),
        torch.arange(0, camera.width, step, dtype=torch.float64),
        indexing="ij",
    )
    pix = torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)
    xy = undistort_pixels(pix, camera, newton_steps=8)
    err_px = ((distort_normalized(xy, camera.distortion) - xd) * xd.new_tensor([camera.fx, camera.fy])).abs().max()
    if not bool(torch.isfinite(err_px)) or float(err_px) > 1e-6:
        raise ConfigError(f"camera: lens distortion {camera.distortion} cannot be inverted over the image (residual {float(err_px):.3g} px)")
    return xy


def _pinhole_rays(camera: PinholeCamera, dtype: torch.dtype, device, step: int = 1) -> Tensor:
    """``((u - cx) / fx, (v - cy) / fy)`` of the pixels ``[::step, ::step]``, computed in ``dtype`` as
    ``backproject_depth`` does."""
    v, u = torch.meshgrid(
        torch.arange(0, camera.height, step, dtype=dtype, device=device),
        torch.arange(0, camera.width, step, dtype=dtype, device=device),
        indexing="ij",
    )
    intr = camera.as_tensor(dtype, device)
    return torch.stack([(u.reshape(-1) - intr[2]) / intr[0], (v.reshape(-1) - intr[3]) / intr[1]], dim=-1)


def _distortion_jacobian(xy: Tensor, distortion: tuple[float, ...]) -> Tensor:
    """(..., 2, 2) derivative of ``distort_normalized`` with respect to ``xy``."""
    j00, j01, j10, j11 = _jacobian_planes(*xy.unbind(-1), distortion)
    return torch.stack([torch.stack([j00, j01], -1), torch.stack([j10, j11], -1)], -2)


def _jacobian_planes(x, y, distortion: tuple[float, ...]):
    """The four entries ``(d x_d / dx, d x_d / dy, d y_d / dx, d y_d / dy)`` of
    ``distort_planes``' derivative at coordinate planes ``x``, ``y`` (tensors or arrays)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = _distortion_terms(distortion)
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d num / d r2
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    radial = num / den
    drad = (dnum * den - num * dden) / (den * den)  # d radial / d r2; d r2 / dx = 2x
    j00 = radial + x * drad * 2 * x + 2 * p1 * y + 6 * p2 * x
    j01 = x * drad * 2 * y + 2 * p1 * x + 2 * p2 * y
    j10 = y * drad * 2 * x + 2 * p1 * x + 2 * p2 * y
    j11 = radial + y * drad * 2 * y + 6 * p1 * y + 2 * p2 * x
    return j00, j01, j10, j11


def backproject_depth(depth: Tensor, intrinsics: Tensor, rays: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Lift every pixel of depth images to 3-D points in the camera frame.

    Args:
        depth: (B, 1, H, W) depth in metres; 0 (or any non-finite or negative value) is invalid.
        intrinsics: (B, 4) or (4,) intrinsics ``(fx, fy, cx, cy)``.
        rays: optional (H*W, 2) or (B, H*W, 2) normalised rays of the pixels
            (``undistorted_rays`` for a camera with lens distortion); when given the points are
            ``(x z, y z, z)`` and ``intrinsics`` is only checked, otherwise the ideal pinhole
            ``((u - cx) / fx z, (v - cy) / fy z, z)``.

    Returns:
        points: (B, H*W, 3) points in metres, row-major pixel order; invalid pixels give (0, 0, 0).
        valid: (B, H*W) bool mask of valid depth.
    """
    dims: dict[str, int] = {}
    check_shape(depth, "B 1 H W", "depth", dims)
    check_float(depth, "depth")
    if intrinsics.dim() == 1:
        intrinsics = intrinsics.expand(depth.shape[0], 4)
    check_shape(intrinsics, "B 4", "intrinsics", dims)
    B, _, H, W = depth.shape
    z = depth.reshape(B, H * W)
    valid = torch.isfinite(z) & (z > 0)
    z = torch.where(valid, z, torch.zeros_like(z))
    if rays is not None:
        if rays.dim() == 2:
            rays = rays[None]
        check_shape(rays, f"R {H * W} 2", "rays")
        if rays.shape[0] not in (1, B):
            raise ShapeError(f"rays: expected a batch of 1 or {B}, got {rays.shape[0]}")
        r = rays.to(depth.dtype)
        return torch.stack([r[..., 0] * z, r[..., 1] * z, z], dim=-1), valid
    v, u = torch.meshgrid(
        torch.arange(H, dtype=depth.dtype, device=depth.device),
        torch.arange(W, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    u, v = u.reshape(1, -1), v.reshape(1, -1)
    intr = intrinsics.to(depth.dtype)
    fx, fy, cx, cy = (intr[:, k : k + 1] for k in range(4))
    points = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], dim=-1)  # (B, H*W, 3)
    return points, valid


def project_points(points_c: Tensor, intrinsics: Tensor, min_depth: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Project camera-frame points to pixel coordinates.

    Args:
        points_c: (..., N, 3) points in the camera frame, metres.
        intrinsics: (..., 4) intrinsics broadcastable against the points' batch dims.
        min_depth: points with ``z <= min_depth`` are marked invalid (their uv is finite but meaningless).

    Returns:
        uv: (..., N, 2) pixel coordinates.
        valid: (..., N) bool mask of points in front of the camera.
    """
    check_shape(points_c, "... N 3", "points_c")
    check_shape(intrinsics, "... 4", "intrinsics")
    z = points_c[..., 2]
    valid = z > min_depth
    z_safe = torch.where(valid, z, torch.ones_like(z))
    intr = intrinsics[..., None, :].to(points_c.dtype)
    u = intr[..., 0] * points_c[..., 0] / z_safe + intr[..., 2]
    v = intr[..., 1] * points_c[..., 1] / z_safe + intr[..., 3]
    return torch.stack([u, v], dim=-1), valid
