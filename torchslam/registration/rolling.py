"""Rolling-shutter frames brought to one instant, to first order in the camera's motion.

A rolling-shutter sensor reads its rows one after another: row ``y`` of an image of ``H`` rows
read out in ``readout`` seconds is seen ``delta(y) = readout (y - (H - 1) / 2) / H`` after the
image's stamp, which belongs to its middle row (top row first). A camera moving with body twist
``xi = (v, w)`` (per second, translation first, in the camera's own coordinates:
``T_wc(t + s) = T_wc(t) exp(s xi)``) sees in row ``y`` the point ``X_row`` that lies at

    X = exp(delta xi) X_row ~ X_row + delta (w x X_row + v)

in the camera at the stamp. Over a frame period (``|delta|`` at most 17 ms at 30 Hz) the
first-order term is exact to well under a millimetre for hand-held motion.

- :func:`correct_points` moves back-projected pixels of a frame to its stamp (what a frame
  registered *to* a keyframe contributes: its points, no resampling).
- :func:`global_shutter_images` resamples working images (grey and depth) onto the pixel grid
  of the camera at the stamp (what a keyframe registered *against* contributes: images).
- :func:`correct_rows` moves points seen at given image rows (ORB keypoints' points, depth
  samples: the sparse front-end's), :func:`features_at_stamp` a frame's ORB features.

Both take the twist as an estimate (the tracker's constant-velocity motion); a zero twist or
``readout`` 0 leaves the input as it is. Batch first: ``(B, ...)`` throughout.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..data.calibration import MAX_READOUT_S
from ..errors import ConfigError, ShapeError, check_shape
from .dense import DenseFrame, DenseImages, DenseLevel, _level_camera, _numpy_ok
from .sparse import FrameFeatures

__all__ = [
    "MAX_READOUT_S", "check_readout", "correct_points", "correct_rows", "dense_frame_at_stamp", "dense_images_at_stamp",
    "features_at_stamp", "global_shutter_images", "row_offsets",
]

# Relative depth step between a pixel and its neighbours' blend below which they are one surface.
_SMOOTH_DEPTH = 0.05


def check_readout(readout: float, name: str = "readout_time") -> float:
    """``readout`` as a float in ``[0, MAX_READOUT_S]`` seconds, else a ConfigError naming ``name``."""
    try:
        r = float(readout)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected seconds, a number in [0, {MAX_READOUT_S}], got {readout!r}") from None
    if not 0.0 <= r <= MAX_READOUT_S:  # False for NaN
        raise ConfigError(f"{name}: expected seconds in [0, {MAX_READOUT_S}] (0: a global shutter), got {readout!r}")
    return r


def row_offsets(h: int, full_height: int, readout: float, dtype: torch.dtype = torch.float64,
                device: torch.device | str = "cpu") -> Tensor:
    """(h,) seconds from the stamp to the instant each row of an ``h``-row image was read.

    The image is the ``full_height``-row sensor image reduced by ``k = full_height / h`` (a
    pyramid level): its row ``r`` covers the sensor rows around ``(r + 0.5) k - 0.5``.
    """
    k = full_height / h
    y = (torch.arange(h, dtype=torch.float64) + 0.5) * k - 0.5
    return (readout * (y - (full_height - 1) / 2) / full_height).to(dtype=dtype, device=device)


def _motion(points: Tensor, twist: Tensor) -> Tensor:
    """(B, N, 3) ``w x X + v`` of points (B, N, 3) under twists (B, 6)."""
    v, w = twist[:, None, :3], twist[:, None, 3:]
    return torch.linalg.cross(w.expand_as(points), points, dim=-1) + v


def correct_points(points: Tensor, valid: Tensor, twist: Tensor, width: int, full_height: int, readout: float) -> Tensor:
    """Back-projected pixels of rolling-shutter images moved to their stamps' camera.

    Args:
        points: (B, h*w, 3) points of each pixel in the camera of its row's instant, row-major.
        valid: (B, h*w) bool; invalid points stay as they are (0, 0, 0).
        twist: (B, 6) body twists per second, translation first (module docstring).
        width: ``w``, pixels per row.
        full_height: rows of the sensor image (``h`` may be a reduced level's).
        readout: seconds from the first row to the last.

    Returns:
        (B, h*w, 3) the points in the camera at the stamp, same dtype.
    """
    dims: dict[str, int] = {}
    check_shape(points, "B N 3", "points", dims)
    check_shape(valid, "B N", "valid", dims)
    check_shape(twist, "B 6", "twist", dims)
    readout = check_readout(readout, "readout")
    N = dims["N"]
    if N % width:
        raise ShapeError(f"width: {width} does not divide the {N} points into rows")
    if readout == 0.0:
        return points
    h = N // width
    delta = row_offsets(h, full_height, readout, points.dtype, points.device)  # (h,)
    if _numpy_ok(points, valid, twist):
        return _correct_points_numpy(points, valid, twist, delta, width)
    return _moved(points, valid, twist, delta.repeat_interleave(width)[None])


def correct_rows(points: Tensor, rows: Tensor, valid: Tensor, twist: Tensor, full_height: int, readout: float) -> Tensor:
    """Points seen at given (sub-pixel) sensor rows moved to their stamps' camera.

    Args:
        points: (B, N, 3) each point in the camera of its row's instant.
        rows: (B, N) the sensor row each was seen at (``y`` of the module docstring; a
            keypoint's ``v``).
        valid: (B, N) bool; invalid points stay as they are.
        twist: (B, 6) body twists per second, translation first.
        full_height: rows of the sensor image.
        readout: seconds from the first row to the last.

    Returns:
        (B, N, 3) the points in the camera at the stamp, same dtype.
    """
    dims: dict[str, int] = {}
    check_shape(points, "B N 3", "points", dims)
    check_shape(rows, "B N", "rows", dims)
    check_shape(valid, "B N", "valid", dims)
    check_shape(twist, "B 6", "twist", dims)
    readout = check_readout(readout, "readout")
    if readout == 0.0:
        return points
    return _moved(points, valid, twist, readout * (rows.to(points.dtype) - (full_height - 1) / 2) / full_height)


def _moved(points: Tensor, valid: Tensor, twist: Tensor, delta: Tensor) -> Tensor:
    """(B, N, 3) ``X + delta (w x X + v)`` of valid points, the invalid ones as they are; ``delta``
    (B, N) or (1, N) seconds from each point's row to the stamp."""
    step = _motion(points, twist.to(dtype=points.dtype, device=points.device))
    return points + step * (delta * valid.to(points.dtype))[..., None]


def features_at_stamp(features: FrameFeatures, twist: Tensor, full_height: int, readout: float) -> FrameFeatures:
    """A frame's ORB features with each keypoint's point moved to the stamp from its row's instant
    (:func:`correct_rows`); keypoints and descriptors stay as read.

    Args:
        features: one frame's features (points (K, 3) in the camera of each keypoint's row).
        twist: (6,) the frame's body twist per second, translation first.
        full_height: rows of the sensor image.
        readout: seconds from the first sensor row to the last.
    """
    if readout == 0.0 or not len(features):
        return features
    pts = correct_rows(features.points[None], features.keypoints[None, :, 1], features.valid[None], twist.reshape(1, 6),
                       full_height, readout)[0]
    return FrameFeatures(features.keypoints, features.descriptors, pts, features.valid)


def _correct_points_numpy(points: Tensor, valid: Tensor, twist: Tensor, delta: Tensor, width: int) -> Tensor:
    """:func:`correct_points` on the host: the same first-order step, component by component on
    contiguous rows (the torch path's cross product over interleaved ``(N, 3)`` points took 4.4 ms
    for a 320x240 level, this 0.65 ms; one thread)."""
    P = points.numpy()
    B, N, _ = P.shape
    out = np.empty_like(P)
    d = delta.numpy()
    for b in range(B):
        vx, vy, vz, wx, wy, wz = (P.dtype.type(t) for t in twist[b].tolist())
        dv = (valid[b].numpy().reshape(-1, width) * d[:, None]).reshape(N)  # 0 for invalid points: unmoved
        X, Y, Z = P[b].T.copy()
        for k, (m, base) in enumerate(((wy * Z - wz * Y + vx, X), (wz * X - wx * Z + vy, Y), (wx * Y - wy * X + vz, Z))):
            m *= dv
            m += base
            out[b, :, k] = m
    return torch.from_numpy(out)


def global_shutter_images(grey: Tensor, depth: Tensor, inside: Tensor | None, fx: float, fy: float, cx: float, cy: float,
                          twist: Tensor, full_height: int, readout: float) -> tuple[Tensor, Tensor, Tensor | None]:
    """Rolling-shutter working images resampled onto the pixel grid of the camera at the stamp.

    For each target pixel ``p`` with depth ``z`` (the image's own at ``p``; the median valid
    depth where it has none) the point ``X = z ray(p)`` is moved to the row that sees it,
    ``X_row = X - delta (w x X + v)``, with that row found by two fixed-point steps. Grey is
    read there bilinearly, depth bilinearly on a smooth surface (its four neighbours valid and
    within 5 % of the nearest pixel's) and else at the nearest pixel, ``inside`` at the nearest
    pixel; the depth read is moved back to the stamp (``z`` of ``Y + delta (w x Y + v)``, ``Y``
    its point). Pixels whose source lies outside the image get depth 0 (and ``inside`` 0).

    Args:
        grey: (B, 1, h, w) grey.
        depth: (B, 1, h, w) depth, metres, 0 = invalid.
        inside: (B, 1, h, w) 0/1 mask of pixels inside the raw image, or None (all inside).
        fx, fy, cx, cy: the (ideal pinhole) intrinsics of the ``h x w`` images.
        twist: (B, 6) body twists per second, translation first.
        full_height: rows of the sensor image the ``h`` rows were reduced from.
        readout: seconds from the first row to the last.

    Returns:
        grey, depth, inside as given (inside None stays None where every source lies inside).
    """
    dims: dict[str, int] = {}
    check_shape(grey, "B 1 h w", "grey", dims)
    check_shape(depth, "B 1 h w", "depth", dims)
    check_shape(twist, "B 6", "twist", dims)
    readout = check_readout(readout, "readout")
    if readout == 0.0:
        return grey, depth, inside
    B, _, h, w = grey.shape
    dt, dev = grey.dtype, grey.device
    # Coordinates as planes (B, N), component by component: the (N, 3) cross products of
    # ``_motion`` took half the time at 320x240 (18.5 -> 9.3 ms per image, one thread).
    vx, vy, vz, wx, wy, wz = (c[:, None] for c in twist.to(dtype=dt, device=dev).unbind(-1))
    delta_rows = row_offsets(h, full_height, readout, dt, dev)  # (h,)
    v, u = torch.meshgrid(torch.arange(h, dtype=dt, device=dev), torch.arange(w, dtype=dt, device=dev), indexing="ij")
    rx, ry = ((u - cx) / fx).reshape(1, -1), ((v - cy) / fy).reshape(1, -1)
    z = depth.reshape(B, -1)
    good = z > 0
    fill = torch.stack([z[b][good[b]].median() if bool(good[b].any()) else z.new_tensor(1.0) for b in range(B)])
    z = torch.where(good, z, fill[:, None])
    X, Y, Z = rx * z, ry * z, z
    mx, my, mz = wy * Z - wz * Y + vx, wz * X - wx * Z + vy, wx * Y - wy * X + vz  # w x X + v
    qv = v.reshape(1, -1).expand(B, -1)
    for _ in range(2):
        d = delta_rows[qv.round().clamp(0, h - 1).long()]
        zy = (Z - mz * d).clamp_min(1e-6)
        qu = (X - mx * d) / zy * fx + cx
        qv = (Y - my * d) / zy * fy + cy
    d = delta_rows[qv.round().clamp(0, h - 1).long()]
    grid = torch.stack([qu * (2.0 / (w - 1)) - 1.0, qv * (2.0 / (h - 1)) - 1.0], dim=-1).view(B, h, w, 2)
    g2 = F.grid_sample(grey, grid, mode="bilinear", padding_mode="border", align_corners=True)
    # Depth bilinearly where its four neighbours are valid and agree (a smooth surface: no bias
    # from the sub-pixel shift), else the nearest pixel's (across an edge, no blend of two surfaces).
    z_near = F.grid_sample(depth, grid, mode="nearest", padding_mode="zeros", align_corners=True).reshape(B, -1)
    z_lin = F.grid_sample(depth, grid, mode="bilinear", padding_mode="zeros", align_corners=True).reshape(B, -1)
    full = F.grid_sample((depth > 0).to(dt), grid, mode="bilinear", padding_mode="zeros", align_corners=True).reshape(B, -1)
    smooth = (full >= 1.0 - 1e-6) & ((z_lin - z_near).abs() <= _SMOOTH_DEPTH * z_near)
    z2 = torch.where(smooth, z_lin, z_near)
    # The read point Y = z2 ray(q) moved back to the stamp: z of Y + d (w x Y + v).
    zs = z2 * (1.0 + d * (wx * (qv - cy) / fy - wy * (qu - cx) / fx)) + d * vz
    inb = (qu >= 0) & (qu <= w - 1) & (qv >= 0) & (qv <= h - 1)
    ok = (z2 > 0) & inb & (zs > 0)
    depth2 = torch.where(ok, zs, torch.zeros_like(zs)).view(B, 1, h, w)
    src_in = inb.to(dt).view(B, 1, h, w)
    if inside is None:
        inside2 = None if bool(src_in.all()) else src_in
    else:
        inside2 = F.grid_sample(inside, grid, mode="nearest", padding_mode="zeros", align_corners=True) * src_in
    return g2, depth2, inside2


def dense_frame_at_stamp(frame: DenseFrame, twist: Tensor, readout: float) -> DenseFrame:
    """A prepared frame whose every level's points are moved to the stamp (:func:`correct_points`);
    its images stay as read (what a frame registered to a keyframe contributes is its points).

    Args:
        frame: B prepared frames of rolling-shutter images.
        twist: (B, 6) or (6,) body twists per second, translation first.
        readout: seconds from the first sensor row to the last.
    """
    if readout == 0.0:
        return frame
    tw = twist.reshape(-1, 6).expand(len(frame), 6)
    H = frame.camera.height
    levels = []
    for lv in frame.levels:
        pts = correct_points(lv.points, lv.valid, tw, lv.grey.shape[-1], H, readout)
        levels.append(DenseLevel(lv.camera, lv.depth_edge_tolerance, lv.grey, lv.depth, lv.inside, pts, lv.valid))
    return DenseFrame(tuple(levels), frame.camera, frame.cfg)


def dense_images_at_stamp(images: DenseImages, twist: Tensor, readout: float) -> DenseImages:
    """Working images resampled to the camera at the stamp (:func:`global_shutter_images`); their
    :meth:`~torchslam.registration.dense.DenseImages.pyramid` is what a keyframe is registered
    against.

    Args:
        images: B frames' working images (undistorted, ideal pinhole).
        twist: (B, 6) or (6,) body twists per second, translation first.
        readout: seconds from the first sensor row to the last.
    """
    if readout == 0.0:
        return images
    camera, grey = images.camera, images.grey
    h, w = grey.shape[-2:]
    k = max(1, round(camera.width / images.cfg.width))
    cam = _level_camera(camera, 1.0 / k, w, h)
    tw = twist.reshape(-1, 6).expand(len(images), 6)
    g, d, inside = global_shutter_images(grey, images.depth, images.inside, cam.fx, cam.fy, cam.cx, cam.cy, tw,
                                         camera.height, readout)
    if inside is not None and images.inside is None and not camera.has_distortion:
        # DenseImages keeps ``inside`` only for a camera with distortion: outside sources have depth 0 already.
        inside = None
    return DenseImages(g, d, inside, camera, images.cfg)
