"""Pinhole camera: intrinsics, back-projection of depth images, projection, pyramid scaling.

Convention:
    Intrinsics as a tensor are ``(..., 4)`` = ``(fx, fy, cx, cy)`` in pixels, with pixel centres
    at integer coordinates (``u = fx x / z + cx``). Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ShapeError, check_float, check_shape

__all__ = ["PinholeCamera", "backproject_depth", "project_points", "scale_intrinsics", "intrinsics_matrix"]


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of one camera and its image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ShapeError(f"PinholeCamera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (self.width > 0 and self.height > 0):
            raise ShapeError(f"PinholeCamera: image size must be positive, got {self.width}x{self.height}")

    def as_tensor(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """Return ``(4,)`` intrinsics ``(fx, fy, cx, cy)``."""
        return torch.tensor([self.fx, self.fy, self.cx, self.cy], dtype=dtype, device=device)

    def scaled(self, factor: float) -> "PinholeCamera":
        """Return the camera of an image resized by ``factor`` (e.g. 0.5 for one pyramid level)."""
        fx, fy, cx, cy = _scale(self.fx, self.fy, self.cx, self.cy, factor, factor)
        return PinholeCamera(fx, fy, cx, cy, max(1, round(self.width * factor)), max(1, round(self.height * factor)))


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


def backproject_depth(depth: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Lift every pixel of depth images to 3-D points in the camera frame.

    Args:
        depth: (B, 1, H, W) depth in metres; 0 (or any non-finite or negative value) is invalid.
        intrinsics: (B, 4) or (4,) intrinsics ``(fx, fy, cx, cy)``.

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
