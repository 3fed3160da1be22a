"""Orthographic re-projection of attitude-aligned point clouds (NI-SLAM §4).

A frame's point cloud is rotated into the keyframe's attitude and projected *orthographically*
onto the keyframe's image plane, so that a camera translation parallel to that plane becomes a
pure image shift and a translation along the optical axis becomes a constant depth offset
(NI-SLAM Eq. (4), (6), (7)).

Convention:
    Points are in the camera frame (x right, y down, z forward, metres). ``rotation`` maps them
    into the keyframe attitude frame: with camera-to-world poses ``T_wc`` it is
    ``R_wk^T @ R_wi`` (the paper's ``R_k R_i^-1``), composed by the caller. A point ``p`` lands in
    pixel ``(col, row) = floor((p_x - c_x) / r + W / 2), floor((p_y - c_y) / r + H / 2)`` where
    ``r`` is the resolution in metres per pixel and ``c`` the image centre offset in metres
    (zero keeps the central axis on the optical axis, as the paper does). Image columns follow
    camera x and rows camera y, so an image shift ``(dx, dy)`` in pixels is a metric shift
    ``r * (dx, dy)`` of the content in camera x and y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cache import FifoCache, tensor_key
from ..errors import ConfigError, DTypeError, InvalidValueError, ShapeError, check_float, check_shape
from ..geometry.camera import distort_planes
from ._select import where

__all__ = [
    "OrthoImages",
    "choose_resolution",
    "grey_from_rgb",
    "orthographic_project",
    "rgbd_to_points",
    "sample_grey",
    "sample_grey_rotated",
    "sample_grey_warped",
]

# ITU-R BT.601 luma weights: the usual grey conversion for 8-bit colour cameras.
_LUMA = (0.299, 0.587, 0.114)


@dataclass(frozen=True)
class OrthoImages:
    """Orthographic grey and depth images with their validity mask.

    Attributes:
        grey: (B, H, W) grey value of the nearest point in each pixel, 0 where invalid.
        depth: (B, H, W) z of the nearest point in the keyframe attitude frame, metres, 0 where invalid.
        valid: (B, H, W) bool, True where at least one point fell into the pixel.
        resolution: (B,) metres per pixel used for the projection.
        center: (B, 2) image centre offset ``(c_x, c_y)`` in metres.
        colour: (B, C, H, W) further per-point values (e.g. RGB) of the same nearest points, 0
            where invalid; None unless ``orthographic_project`` was given ``colour``.
    """

    grey: Tensor
    depth: Tensor
    valid: Tensor
    resolution: Tensor
    center: Tensor
    colour: Tensor | None = None


def grey_from_rgb(rgb: Tensor) -> Tensor:
    """Convert colour images to per-pixel grey values in the point order of ``geometry.backproject_depth``.

    Args:
        rgb: (B, 3, H, W) colour in [0, 1].

    Returns:
        (B, H*W) BT.601 luma in [0, 1], row-major pixel order.
    """
    check_shape(rgb, "B 3 H W", "rgb")
    check_float(rgb, "rgb")
    w = rgb.new_tensor(_LUMA)
    if torch.is_grad_enabled() and rgb.requires_grad:
        return (rgb * w.view(1, 3, 1, 1)).sum(dim=1).flatten(1)
    # The channel sum in its order, r w_r + g w_g then + b w_b, accumulated in one plane: the
    # values of ``(rgb * w).sum(dim=1)`` without its (B, 3, H, W) product.
    grey = torch.mul(rgb[:, 0], w[0])
    grey.add_(rgb[:, 1] * w[1])
    grey.add_(rgb[:, 2] * w[2])
    return grey.flatten(1)


def rgbd_to_points(
    rgb: Tensor, depth: Tensor, intrinsics: Tensor, rays: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Lift registered colour and depth images to a grey point cloud in the camera frame.

    Args:
        rgb: (B, 3, H, W) colour in [0, 1].
        depth: (B, 1, H, W) depth in metres, 0 = invalid.
        intrinsics: (B, 4) or (4,) ``(fx, fy, cx, cy)`` in pixels.
        rays: optional (H*W, 2) normalised rays of the pixels with the lens distortion removed
            (``geometry.undistorted_rays``); the points are then ``(x z, y z, z)``. ``None``
            uses the ideal pinhole factors ``(u - c) / f``.

    Returns:
        points: (B, H*W, 3) camera-frame points, metres, 0 where invalid: the transposed view of
            (B, 3, H*W) coordinate planes (``points.transpose(1, 2)`` is contiguous).
        grey: (B, H*W) grey value of each point.
        valid: (B, H*W) bool, True where depth is valid.
    """
    dims: dict[str, int] = {}
    check_shape(rgb, "B 3 H W", "rgb", dims)
    check_shape(depth, "B 1 H W", "depth", dims)
    check_float(depth, "depth")
    B, _, H, W = depth.shape
    intr = intrinsics.expand(B, 4) if intrinsics.dim() == 1 else intrinsics
    check_shape(intr, "B 4", "intrinsics", dims)
    # Same arithmetic as ``backproject_depth`` ((u - c) / f * z, bit-identical), with the per-pixel
    # factors (u - c) / f kept between frames of one camera instead of rebuilt from a meshgrid.
    if rays is None:
        rx, ry = _pixel_rays(intr.to(depth.dtype), H, W)
    else:
        check_shape(rays, f"{H * W} 2", "rays")
        check_float(rays, "rays")
        rx, ry = rays.to(depth.dtype)[None].unbind(-1)  # (1, H*W) each
    z = depth.reshape(B, H * W)
    # isfinite(z) & (z > 0) in two cheap comparisons: NaN fails both, +inf the second.
    valid = (z > 0) & (z < math.inf)
    z = where(valid, z, 0.0)
    # The points are stored one coordinate per plane, (B, 3, H*W), and returned as the (B, H*W, 3)
    # transposed view: the rotations downstream (``_rotate_planar``) then read contiguous
    # planes (a well-shaped GEMM, unlike interleaved xyz), and stacking planes is a plain copy
    # where interleaving copies element by element. The values are the same.
    if z.requires_grad or rx.requires_grad:
        planes = torch.stack([rx * z, ry * z, z], dim=1)
    else:  # the products written into their planes directly, without the intermediate copies
        planes = z.new_empty(B, 3, H * W)
        torch.mul(rx, z, out=planes[:, 0])
        torch.mul(ry, z, out=planes[:, 1])
        planes[:, 2] = z
    points = planes.transpose(1, 2)  # (B, H*W, 3)
    return points, grey_from_rgb(rgb).to(points.dtype), valid


# (intrinsics tensor, (rx, ry)) per (H, W, intrinsics identity): the tensor is kept so its id stays unique.
_RAYS: FifoCache[tuple[Tensor, tuple[Tensor, Tensor]]] = FifoCache(8)


def _pixel_rays(intr: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """((B, H*W), (B, H*W)) factors ``(u - c_x) / f_x`` and ``(v - c_y) / f_y``, cached per intrinsics tensor.

    The key is the tensor's identity and version (``cache.tensor_key``), never its values, so a
    lookup does not wait for the device; a caller that passes the same intrinsics tensor every
    frame hits, a new tensor with equal values recomputes the same factors.
    """
    if intr.requires_grad:
        return _compute_pixel_rays(intr, H, W)
    return _RAYS.get_or_compute((H, W, *tensor_key(intr)), lambda: (intr, _compute_pixel_rays(intr, H, W)))[1]


def _compute_pixel_rays(intr: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    v, u = torch.meshgrid(
        torch.arange(H, dtype=intr.dtype, device=intr.device),
        torch.arange(W, dtype=intr.dtype, device=intr.device),
        indexing="ij",
    )
    u, v = u.reshape(1, -1), v.reshape(1, -1)
    fx, fy, cx, cy = (intr[:, k : k + 1] for k in range(4))
    return ((u - cx) / fx, (v - cy) / fy)


def sample_grey(
    rgb: Tensor,
    points: Tensor,
    valid: Tensor,
    rotation: Tensor,
    intrinsics: Tensor,
    grey_image: Tensor | None = None,
    distortion: tuple[float, ...] | None = None,
) -> tuple[Tensor, Tensor]:
    """Grey values of points seen from a rotated camera: the colour image taken at another instant.

    A sensor whose colour and depth images are taken at different instants (TUM fr1: up to
    ±17 ms apart) pairs each depth pixel with the colour pixel at the same image position,
    which, while the camera turns, shows a different scene point: at 40 °/s a 15 ms gap moves
    the texture ~5 px against the geometry. Given the rotation from the depth camera into the
    colour camera (from the attitude stream at the two timestamps), each point ``p`` is moved
    to ``R p``, projected with the pinhole intrinsics and the grey image is sampled there
    bilinearly. The translation in between is not known to the attitude stream and is ignored.

    Args:
        rgb: (B, 3, H, W) colour in [0, 1].
        points: (B, H*W, 3) depth-camera points, metres (``rgbd_to_points`` order).
        valid: (B, H*W) bool validity of the points.
        rotation: (B, 3, 3) rotation from the depth camera's frame into the colour camera's
            (``R_wc^T R_wd`` with camera-to-world attitudes).
        intrinsics: (B, 4) or (4,) ``(fx, fy, cx, cy)`` of the colour image, pixels.
        grey_image: (B, H*W) ``grey_from_rgb(rgb)`` where the caller already has it (e.g. from
            ``rgbd_to_points``), so it is not computed twice; ``None`` computes it.
        distortion: lens distortion of the colour camera (``PinholeCamera.distortion``); the
            rotated points are then distorted (``geometry.distort_normalized``) before the
            intrinsics map them to pixels. ``None`` projects with the ideal pinhole.

    Returns:
        grey: (B, H*W) BT.601 grey at the re-projected positions (0 where not valid).
        valid: (B, H*W) bool, the input validity and the re-projection in front of the camera
            and inside the colour image.
    """
    dims: dict[str, int] = {}
    check_shape(rgb, "B 3 H W", "rgb", dims)
    check_float(rgb, "rgb")
    _check_points(points, valid, dims)
    check_shape(rotation, "B 3 3", "rotation", dims)
    check_float(rotation, "rotation")
    B, _, H, W = rgb.shape
    if points.shape[1] != H * W:
        raise ShapeError(f"points: expected H*W = {H * W} points of the ({H}, {W}) image, got {points.shape[1]}")
    intr = intrinsics.to(points.dtype)
    if intr.dim() == 1:
        intr = intr[None].expand(B, 4)
    check_shape(intr, "B 4", "intrinsics", dims)
    if distortion is not None and any(c != 0.0 for c in distortion):
        gx, gy, front = _project_distorted(points, rotation.to(points.dtype), intr, distortion, H, W)
    else:
        gx, gy, front = _project_pinhole(points, rotation.to(points.dtype), intr, H, W)
    # u in [-0.5, W - 0.5] and v in [-0.5, H - 0.5] are |g| <= 1.
    inside = front & (gx.abs() <= 1) & (gy.abs() <= 1)  # (B, N)
    # Interleaved as a complex tensor's (real, imag) pairs: bit-identical to stacking on a new
    # last axis, which copies element by element.
    grid = torch.view_as_real(torch.complex(gx, gy)).view(B, H, W, 2)
    ok = valid & inside
    return _sample_grey_at(_grey_image(rgb, grey_image), grid, ok, H, W, points.dtype), ok


def _grey_image(rgb: Tensor, grey_image: Tensor | None) -> Tensor:
    """(B, H*W) grey of ``rgb``: the caller's ``grey_image`` (checked) or computed."""
    if grey_image is None:
        return grey_from_rgb(rgb)
    B, _, H, W = rgb.shape
    check_shape(grey_image, f"{B} {H * W}", "grey_image")
    check_float(grey_image, "grey_image")
    return grey_image.to(rgb.dtype)


def _sample_grey_at(grey_image: Tensor, grid: Tensor, ok: Tensor, H: int, W: int, dtype: torch.dtype) -> Tensor:
    """(B, H*W) bilinear samples of the (B, H*W) grey images at the (B, H, W, 2) ``grid_sample``
    coordinates (border replication), 0 where not ``ok``."""
    img = grey_image.view(-1, 1, H, W)
    grey = F.grid_sample(img, grid.to(img.dtype), mode="bilinear", padding_mode="border", align_corners=False)
    return where(ok, grey.flatten(1).to(dtype), 0.0)


def sample_grey_rotated(
    rgb: Tensor,
    valid: Tensor,
    rotation: Tensor,
    intrinsics: Tensor,
    rays: Tensor | None = None,
    grey_image: Tensor | None = None,
    distortion: tuple[float, ...] | None = None,
    step: int = 8,
    points: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``sample_grey`` for a pure rotation, without the points: one smooth warp per image.

    A rotation moves every point of a pixel's ray to the same place in the other image, so the
    colour pixel of depth pixel ``u`` does not depend on the depth: it is the projection (through
    the lens) of ``R ray(u)``. That warp is computed exactly on a lattice of nodes about ``step``
    pixels apart (spanning the image corners) and interpolated bilinearly in between; the affine
    part of the warp (the identity, and every pinhole warp's first order) is reproduced exactly
    and the rest is smooth: with the TUM fr1 lens at 640 x 480 and the default step the sampling
    positions differ from ``sample_grey``'s by at most 0.008 px for a 0.4 degree rotation and
    0.02 px for 1.1 degrees (tested at the equivalent quarter size), at a fraction of the cost
    (one rotation per node, no per-point distortion).

    Args:
        rgb: (B, 3, H, W) colour in [0, 1].
        valid: (B, H*W) bool validity of the depth pixels.
        rotation: (B, 3, 3) rotation from the depth camera's frame into the colour camera's.
        intrinsics: (B, 4) or (4,) ``(fx, fy, cx, cy)``, pixels.
        rays: (H*W, 2) normalised rays of the pixels (``geometry.undistorted_rays``); ``None``:
            the pinhole rays of ``intrinsics``.
        grey_image: (B, H*W) ``grey_from_rgb(rgb)`` if the caller has it.
        distortion: lens distortion applied to the rotated rays (``sample_grey``).
        step: approximate node spacing, pixels (>= 1).
        points: (B, H*W, 3) the depth pixels' points (``rgbd_to_points``). Only items whose
            rotation turns part of the image behind the camera use them: those are sampled per
            point by ``sample_grey``; the others never depend on them.

    Returns:
        As ``sample_grey``: (B, H*W) grey (0 where not valid) and (B, H*W) bool validity.

    Raises:
        InvalidValueError: an item's rotation turns part of the image behind the camera and no
            ``points`` were given.
    """
    grey_image = _grey_image(rgb, grey_image)
    grey, ok, behind = sample_grey_warped(rgb, valid, rotation, intrinsics, rays, grey_image, distortion, step)
    if bool(behind.any()):  # reads the flags back: one synchronisation (``sample_grey_warped`` has none)
        if points is None:
            raise InvalidValueError("rotation: turns part of the image behind the camera; pass the points (or use sample_grey)")
        idx = behind.nonzero().flatten()
        intr = intrinsics.to(grey.dtype).expand(rgb.shape[0], 4)
        g, v = sample_grey(rgb[idx], points[idx], valid[idx], rotation[idx], intr[idx], grey_image[idx], distortion)
        grey, ok = grey.index_copy(0, idx, g.to(grey.dtype)), ok.index_copy(0, idx, v)
    return grey, ok


def sample_grey_warped(
    rgb: Tensor,
    valid: Tensor,
    rotation: Tensor,
    intrinsics: Tensor,
    rays: Tensor | None = None,
    grey_image: Tensor | None = None,
    distortion: tuple[float, ...] | None = None,
    step: int = 8,
) -> tuple[Tensor, Tensor, Tensor]:
    """The warp of ``sample_grey_rotated`` alone, which never waits for the device.

    Arguments as ``sample_grey_rotated``'s (without ``points``).

    Returns:
        grey: (B, H*W) grey at the warped positions (0 where not valid).
        valid: (B, H*W) bool validity.
        behind: (B,) bool, items whose rotation turns part of the image behind the camera: their
            warp is meaningless and the caller samples them per point (``sample_grey``).
    """
    dims: dict[str, int] = {}
    check_shape(rgb, "B 3 H W", "rgb", dims)
    check_float(rgb, "rgb")
    B, _, H, W = rgb.shape
    check_shape(valid, f"{B} {H * W}", "valid")
    check_shape(rotation, "B 3 3", "rotation", dims)
    check_float(rotation, "rotation")
    if not (isinstance(step, int) and step >= 1):
        raise ConfigError(f"step: expected a positive integer, got {step!r}")
    dtype, dev = rgb.dtype, rgb.device
    intr = intrinsics.to(dtype)
    if intr.dim() == 1:
        intr = intr[None].expand(B, 4)
    check_shape(intr, "B 4", "intrinsics", dims)
    hc, wc = max(2, -(-(H - 1) // step) + 1), max(2, -(-(W - 1) // step) + 1)
    vn = torch.linspace(0, H - 1, hc, dtype=dtype, device=dev)
    un = torch.linspace(0, W - 1, wc, dtype=dtype, device=dev)
    if rays is None:
        rx = (un[None, None, :] - intr[:, 2, None, None]) / intr[:, 0, None, None]  # (B, 1, wc)
        ry = (vn[None, :, None] - intr[:, 3, None, None]) / intr[:, 1, None, None]  # (B, hc, 1)
        rx, ry = rx.expand(B, hc, wc), ry.expand(B, hc, wc)
    else:
        check_shape(rays, f"{H * W} 2", "rays")
        check_float(rays, "rays")
        node = _node_rays(rays, dtype, H, W, vn, un)
        rx, ry = node[0].expand(B, hc, wc), node[1].expand(B, hc, wc)
    # The nodes' rays as points at unit depth: a pure rotation moves the whole ray alike.
    nodes = torch.stack([rx.reshape(B, -1), ry.reshape(B, -1), torch.ones_like(rx).reshape(B, -1)], dim=-1)
    R = rotation.to(dev, dtype)
    if distortion is not None and any(c != 0.0 for c in distortion):
        gx, gy, front = _project_distorted(nodes, R, intr, distortion, H, W)
    else:
        gx, gy, front = _project_pinhole(nodes, R, intr, H, W)
    behind = ~front.all(dim=1)  # (B,) items the warp cannot serve
    coarse = torch.stack([gx, gy], dim=1).view(B, 2, hc, wc)
    grid = F.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=True)  # (B, 2, H, W)
    inside = ((grid[:, 0].abs() <= 1) & (grid[:, 1].abs() <= 1)).flatten(1)
    grey_image = _grey_image(rgb, grey_image)
    ok = valid & inside
    grey = _sample_grey_at(grey_image, grid.permute(0, 2, 3, 1), ok, H, W, dtype)
    return grey, ok, behind


# (rays tensor, (2, hc, wc) node rays) per (rays identity and version, dtype, node lattice).
_NODE_RAYS: FifoCache[tuple[Tensor, Tensor]] = FifoCache(8)


def _node_rays(rays: Tensor, dtype: torch.dtype, H: int, W: int, vn: Tensor, un: Tensor) -> Tensor:
    """(2, hc, wc) rays at the (fractional) node pixels ``vn`` x ``un``, bilinear in the per-pixel ray image.

    They depend on the sequence's rays alone, so they are kept per rays tensor (``cache.tensor_key``:
    its identity and version, never its values), as ``_pixel_rays`` keeps the pinhole factors.
    """

    def compute() -> Tensor:
        img = rays.to(dtype).T.reshape(1, 2, H, W)
        gv, gu = torch.meshgrid(2 * vn / max(H - 1, 1) - 1, 2 * un / max(W - 1, 1) - 1, indexing="ij")
        return F.grid_sample(img, torch.stack([gu, gv], dim=-1)[None], mode="bilinear", align_corners=True)[0]

    if rays.requires_grad:
        return compute()
    key = (H, W, len(vn), len(un), dtype, *tensor_key(rays))
    return _NODE_RAYS.get_or_compute(key, lambda: (rays, compute()))[1]


# The projections below keep one coordinate per tensor ((B, N) planes): the rotated points come
# out of ``_rotate_planar`` as planes, and interleaving them into (B, N, 2) before the
# element-wise arithmetic would make every later op strided. Only the final grid is interleaved,
# once, as ``grid_sample`` needs it.


def _project_pinhole(points: Tensor, rotation: Tensor, intr: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """(B, N) grid_sample coordinates ``gx``, ``gy`` of rotated points under the pinhole, and (B, N) z > 0."""
    B = points.shape[0]
    # Rotation, pinhole projection and grid_sample's normalised coordinates in one 3x3 map:
    # gx = (2u + 1) / W - 1 with u = fx x / z + cx, i.e. the rows of S K R applied to p, over z.
    # The third row of S K is (0, 0, 1), so n[:, 2] is the rotated z itself.
    S = torch.zeros(B, 3, 3, dtype=points.dtype, device=points.device)
    S[:, 0, 0] = 2 * intr[:, 0] / W
    S[:, 0, 2] = (2 * intr[:, 2] + 1) / W - 1
    S[:, 1, 1] = 2 * intr[:, 1] / H
    S[:, 1, 2] = (2 * intr[:, 3] + 1) / H - 1
    S[:, 2, 2] = 1
    nx, ny, z = _rotate_planar(points, S @ rotation).unbind(1)  # (B, N) each
    front = z > 0
    z = where(front, z, 1.0)
    return nx / z, ny / z, front


def _project_distorted(
    points: Tensor, rotation: Tensor, intr: Tensor, distortion: tuple[float, ...], H: int, W: int
) -> tuple[Tensor, Tensor, Tensor]:
    """As ``_project_pinhole`` with the Brown-Conrady distortion applied to ``(x / z, y / z)``."""
    nx, ny, z = _rotate_planar(points, rotation).unbind(1)  # (B, N) each
    front = z > 0
    z = where(front, z, 1.0)
    xd, yd = distort_planes(nx / z, ny / z, distortion)  # distorted normalised coordinates
    # gx = (2u + 1) / W - 1 with u = fx x_d + cx (and likewise for v).
    gx = xd * (2 * intr[:, 0:1] / W) + ((2 * intr[:, 2:3] + 1) / W - 1)
    gy = yd * (2 * intr[:, 1:2] / H) + ((2 * intr[:, 3:4] + 1) / H - 1)
    return gx, gy, front


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    if len(size) != 2 or not all(isinstance(s, int) and s > 0 for s in size):
        raise ShapeError(f"size: expected (height, width) of positive ints, got {size!r}")
    return int(size[0]), int(size[1])


def _check_points(points: Tensor, valid: Tensor, dims: dict[str, int]) -> None:
    check_shape(points, "B N 3", "points", dims)
    check_float(points, "points")
    check_shape(valid, "B N", "valid", dims)
    if valid.dtype != torch.bool:
        raise DTypeError(f"valid: expected a bool mask, got {valid.dtype}")


def _rotation_and_center(
    points: Tensor, rotation: Tensor | None, center: Tensor | None, dims: dict[str, int]
) -> tuple[Tensor | None, Tensor]:
    if rotation is not None:
        check_shape(rotation, "B 3 3", "rotation", dims)
        check_float(rotation, "rotation")
        rotation = rotation.to(points.dtype)
    if center is None:
        center = points.new_zeros(points.shape[0], 2)
    else:
        check_shape(center, "B 2", "center", dims)
        center = center.to(points.dtype)
    return rotation, center


def _rotate_planar(points: Tensor, rotation: Tensor | None) -> Tensor:
    """(B, 3, N) rotated points, one coordinate per row.

    ``R @ P^T`` with the (B, N, 3) points read as a transposed matrix is one well-shaped GEMM
    (faster than the equivalent ``einsum`` over the point axis on CPU, and bit-identical to it) and leaves each coordinate contiguous for the element-wise code after.
    """
    pt = points.transpose(1, 2)
    return pt if rotation is None else torch.matmul(rotation, pt)


def _rotate(points: Tensor, rotation: Tensor | None) -> Tensor:
    if rotation is None:
        return points
    return _rotate_planar(points, rotation).transpose(1, 2)  # (B, N, 3)


def choose_resolution(
    points: Tensor,
    valid: Tensor,
    size: tuple[int, int] = (360, 480),
    coverage: float = 0.8,
    sample_step: int = 25,
    rotation: Tensor | None = None,
    center: Tensor | None = None,
    min_resolution: float = 1e-4,
) -> Tensor:
    """Pick the orthographic resolution ``r_k`` so the image covers a fraction of the cloud (NI-SLAM §4.2).

    Every ``sample_step``-th point is taken (the paper samples one point in 25). A sampled point
    with aligned coordinates ``(x, y)`` falls inside an ``H x W`` image of resolution ``r`` when
    ``|x - c_x| <= r W / 2`` and ``|y - c_y| <= r H / 2``, i.e. when
    ``r >= q = max(|x - c_x| / (W / 2), |y - c_y| / (H / 2))``. The paper searches for the
    smallest ``r`` covering ``coverage`` of the points; here it is found in closed form as the
    ``ceil(coverage * n)``-th smallest ``q`` among the ``n`` valid samples (an order statistic,
    no interpolation), enlarged by a relative ``1e-6`` so that sample itself lands inside.

    Args:
        points: (B, N, 3) camera-frame points, metres.
        valid: (B, N) bool validity of the points.
        size: ``(H, W)`` of the orthographic image in pixels.
        coverage: fraction of valid sampled points that must fall inside, in (0, 1].
        sample_step: take points ``0, step, 2 step, ...``.
        rotation: (B, 3, 3) rotation into the keyframe attitude; ``None`` = identity (the
            keyframe's own cloud, which is when the paper updates ``r_k``).
        center: (B, 2) image centre offset in metres; ``None`` = zero (optical axis).
        min_resolution: lower bound in metres per pixel, so a cloud collapsed onto the axis
            cannot produce ``r = 0``.

    Returns:
        (B,) resolution in metres per pixel. Items without any valid sampled point get NaN
        (the caller decides what to do; nothing can be covered).
    """
    dims: dict[str, int] = {}
    _check_points(points, valid, dims)
    H, W = _check_size(size)
    if not (0.0 < coverage <= 1.0):
        raise ConfigError(f"coverage: expected a fraction in (0, 1], got {coverage!r}")
    if not (isinstance(sample_step, int) and sample_step >= 1):
        raise ConfigError(f"sample_step: expected a positive int, got {sample_step!r}")
    rotation, center = _rotation_and_center(points, rotation, center, dims)
    pts = _rotate(points[:, ::sample_step], rotation)  # (B, M, 3)
    ok = valid[:, ::sample_step] & torch.isfinite(pts).all(dim=-1)
    need = torch.maximum(
        (pts[..., 0] - center[:, None, 0]).abs() / (W / 2),
        (pts[..., 1] - center[:, None, 1]).abs() / (H / 2),
    )  # (B, M)
    need = torch.where(ok, need, torch.full_like(need, math.inf))
    ordered = need.sort(dim=1).values
    n = ok.sum(dim=1)  # (B,)
    k = (torch.ceil(coverage * n.to(points.dtype)).long() - 1).clamp(min=0, max=max(ordered.shape[1] - 1, 0))
    r = ordered.gather(1, k[:, None])[:, 0] * (1.0 + 1e-6)
    r = r.clamp_min(min_resolution)
    return torch.where(n > 0, r, torch.full_like(r, math.nan))


_POINT_IDS: FifoCache[Tensor] = FifoCache(8)


def _below(W: int, H: int, dtype: torch.dtype, device) -> tuple[float, float]:
    """The largest values of ``dtype`` below ``W`` and ``H``, as Python floats (exact in ``dtype``)."""
    top = torch.tensor([float(W), float(H)], dtype=dtype)
    w_max, h_max = torch.nextafter(top, torch.zeros_like(top)).tolist()
    return w_max, h_max


def _point_ids(n: int, device) -> Tensor:
    """``arange(n)`` as int64, kept per (n, device): the z-buffer keys need it for every frame."""
    return _POINT_IDS.get_or_compute((n, torch.device(device)), lambda: torch.arange(n, device=device))


def orthographic_project(
    points: Tensor,
    grey: Tensor,
    valid: Tensor,
    rotation: Tensor | None,
    resolution: Tensor,
    size: tuple[int, int] = (360, 480),
    center: Tensor | None = None,
    colour: Tensor | None = None,
) -> OrthoImages:
    """Render attitude-aligned points into orthographic grey and depth images (NI-SLAM Eq. (4), (6), (7)).

    Each valid point is rotated by ``rotation`` and dropped into pixel
    ``(floor((x - c_x) / r + W / 2), floor((y - c_y) / r + H / 2))``; points outside the image are
    cropped. Where several points share a pixel the one with the smallest ``z`` (nearest to the
    viewer) wins; ties (z equal in float32) go to the lowest point index, so the result is
    deterministic.

    The z-buffer is a single ``scatter_reduce("amin")`` over flattened ``(b, pixel)`` indices
    (no loop over the batch or the points) of 64-bit keys that pack an order-preserving integer
    image of each point's float32 z above its flat index; the winner's grey and z (in the
    input dtype) are then gathered. The gather keeps the output differentiable with respect to
    ``grey`` and the points' z (the pixel assignment itself is discrete).

    Args:
        points: (B, N, 3) camera-frame points, metres.
        grey: (B, N) grey value per point.
        valid: (B, N) bool validity of the points.
        rotation: (B, 3, 3) rotation into the keyframe attitude, or ``None`` for identity.
        resolution: (B,) metres per pixel ``r_k``. Items with a non-positive or non-finite
            resolution give an empty (all-invalid) image.
        size: ``(H, W)`` of the output images in pixels.
        center: (B, 2) image centre offset ``(c_x, c_y)`` in metres; ``None`` = zero.
        colour: (B, C, N) further values per point (e.g. the RGB the grey came from), rendered
            with the same z-buffer winners into ``OrthoImages.colour``; ``None``: none.

    Returns:
        OrthoImages with (B, H, W) grey, depth, valid (and (B, C, H, W) colour) in the dtype of
        ``points``.
    """
    dims: dict[str, int] = {}
    _check_points(points, valid, dims)
    check_shape(grey, "B N", "grey", dims)
    check_float(grey, "grey")
    check_shape(resolution, "B", "resolution", dims)
    check_float(resolution, "resolution")
    if colour is not None:
        check_shape(colour, "B C N", "colour", dims)
        check_float(colour, "colour")
    H, W = _check_size(size)
    rotation, center = _rotation_and_center(points, rotation, center, dims)
    B, N, _ = points.shape
    if B * N >= 2**32:
        raise ShapeError(f"points: at most 2^32 points per call fit the z-buffer keys, got {B} x {N}")
    HW = H * W
    q = _rotate_planar(points, rotation)  # (B, 3, N)
    x, y, z = q.unbind(1)
    r = resolution.to(q.dtype)[:, None]  # (B, 1)
    inv_r = 1.0 / r
    u = torch.addcmul(W / 2 - center[:, 0:1] * inv_r, x, inv_r)  # (B, N) = (x - c_x) / r + W / 2
    v = torch.addcmul(H / 2 - center[:, 1:2] * inv_r, y, inv_r)
    # 0 <= u < W is u == clamp(u, 0, W-) with W- the largest float below W, and NaN/inf (bad r,
    # bad points) fail the comparison: one clamp and one comparison per axis, and the clamped
    # coordinate is the one the pixel index truncates (to W - 1 at most, as a clamp to W - 1 would).
    w_max, h_max = _below(W, H, q.dtype, q.device)
    uc = u.clamp(min=0, max=w_max)
    vc = v.clamp(min=0, max=h_max)
    inside = valid & (r > 0)
    inside &= uc == u
    inside &= vc == v
    inside &= z.abs() < math.inf  # isfinite(z) (NaN fails the comparison), in a third of the time
    # Truncation is floor for the non-negative clamped coordinates; the points outside (including
    # NaN) are replaced by the trash slot below, whatever integer they became. Pixel indices fit
    # int32 (checked above); only the scatter needs them as int64.
    idt = torch.int32 if B * HW < 2**31 else torch.int64
    pix = vc.to(idt).mul_(W).add_(uc.to(idt))
    if B > 1:
        pix += torch.arange(0, B * HW, HW, dtype=idt, device=q.device)[:, None]
    trash = B * HW  # one extra slot collects every point that is not rendered
    flat = where(inside, pix, trash).flatten().long()  # (B*N,)
    # One scatter does the whole z-buffer: each point's key packs an order-preserving integer
    # image of its float32 z (high 32 bits) with its flat point index (low 32 bits), so the
    # per-pixel minimum key is the nearest point, ties going to the lowest index.
    bits = z.detach().to(torch.float32).contiguous().view(torch.int32)
    zkey = (bits ^ ((bits >> 31) & 0x7FFFFFFF)).flatten().to(torch.int64)  # monotonic in z
    key = zkey.bitwise_left_shift_(32).bitwise_or_(_point_ids(B * N, q.device))
    empty = torch.iinfo(torch.int64).max
    best = torch.full((trash + 1,), empty, dtype=torch.int64, device=q.device)
    best = best.scatter_reduce_(0, flat, key, reduce="amin", include_self=True)[:trash]  # (B*H*W,)
    pix_valid = best != empty
    src = best.bitwise_and_(0xFFFFFFFF).clamp_(max=B * N - 1)
    out_grey = where(pix_valid, grey.to(q.dtype).flatten().index_select(0, src), 0.0)
    out_depth = where(pix_valid, z.flatten().index_select(0, src), 0.0)
    out_colour = None
    if colour is not None:
        C = colour.shape[1]
        picked = colour.to(q.dtype).transpose(0, 1).reshape(C, B * N).index_select(1, src)  # (C, B*H*W)
        out_colour = where(pix_valid, picked, 0.0).view(C, B, H, W).transpose(0, 1)
    return OrthoImages(
        grey=out_grey.view(B, H, W),
        depth=out_depth.view(B, H, W),
        valid=pix_valid.view(B, H, W),
        resolution=resolution.to(q.dtype),
        center=center,
        colour=out_colour,
    )
