"""Synthetic RGB-D-inertial sequences: a procedurally textured room rendered by batched ray casting.

The scene is a 6 x 6 x 3 m room seen from inside, furnished with boxes along the walls (some
stacked), flat posters on the walls, free-standing tilted panels in the corners and a rug. Every
primitive is an oriented box (a flat panel is a box with one zero half-extent). The renderer
intersects their faces rather than slab-testing whole boxes: for a convex box the nearest
front-facing face hit is the slab test's entry point, and a per-face intersection yields the
texel address with per-face constants instead of per-pixel face selection. Textures are built once per face from multi-octave value noise, hard-edged
blobs, checkers, stripes and rectangles, shaded by a fixed light, and stored in one texel atlas;
everything is deterministic from the seed.

Rendering (``SceneRenderer``) casts one ray per pixel for a batch of frames at once:

1. Camera rays ``((u - cx) / fx, (v - cy) / fy, 1)`` are precomputed in 16 x 16 tile order. With
   a unit z component the ray parameter at a hit *is* the depth along the optical axis.
2. Every face is a textured rectangle. For each frame and each face whose visible side faces
   the camera, the near-plane-clipped projection of its corners gives the screen tiles it can
   cover; only overlapping (frame, tile, face) triples are intersected, so the work follows the
   faces' screen area (about two candidates per pixel) instead of pixels x faces.
3. A candidate is a ray-plane intersection tested against the rectangle, which also yields the
   texel address; the nearest candidate per pixel wins (a min over per-tile slots), and the
   texel atlas is sampled bilinearly at the winner's address.

Depth is exact up to float32 round-off (about 1e-6 m); a Kinect-like noise model can be applied
on top: Gaussian noise with sigma_z = k z^2, random holes and quantisation to 1 / depth_scale m.
An IMU (200 Hz gyroscope and accelerometer with white noise and bias random walk) is simulated
from the analytic trajectory, whose velocity, acceleration and angular rate come from automatic
differentiation, and is run through the attitude filter of :mod:`torchslam.imu`.

Convention:
    World frame: z up, gravity ``(0, 0, -gravity)``; the room spans x, y in [-3, 3] m and z in
    [0, 3] m. Camera frame: x right, y down, z forward (OpenCV); poses are camera-to-world
    ``T_wc``. The IMU frame is the camera frame (identity extrinsics).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import threading
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable, ClassVar, Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, FieldError, Limit, check_float, check_limits, check_shape
from ..geometry import PinholeCamera, se3_from_Rt, so3_exp, vex
from ..imu import AttitudeStream, ImuData, ImuNoise, Kinematics, ahrs_attitude, simulate_imu, time_derivatives
from .calibration import DEPTH_SCALE_RANGE, intrinsics_problem
from .frame import Frame, Sequence
from .trajectory import Trajectory, write_tum_trajectory

__all__ = [
    "SYNTHETIC_TRAJECTORIES",
    "TUM_FOLDER_ENTRIES",
    "RenderOutput",
    "Scene",
    "SceneRenderer",
    "SyntheticConfig",
    "SyntheticSequence",
    "build_scene",
    "camera_from_config",
    "generate_sequence",
    "kinect_depth_noise",
    "synthetic_kinematics",
    "synthetic_trajectory",
    "write_tum_folder",
]

logger = logging.getLogger(__name__)

SYNTHETIC_TRAJECTORIES = ("orbit", "translate", "loop", "handheld")

ROOM_CENTER = (0.0, 0.0, 1.5)
ROOM_HALF = (3.0, 3.0, 1.5)
# TUM freiburg1 colour intrinsics at 640 x 480.
_FR1 = (517.3, 516.5, 318.6, 255.3, 640, 480)
# Light direction (world) for the baked face shading.
_LIGHT = (0.35, 0.55, 1.0)
_TILE = 16


# --------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class SyntheticConfig:
    """Settings of a synthetic RGB-D-inertial sequence.

    Attributes:
        frames: number of frames.
        width, height: image size, pixels.
        fps: frame rate, Hz; frame k is at ``k / fps`` seconds.
        seed: seeds the scene layout, textures, hand-held shake, depth noise and IMU noise.
        trajectory: "orbit" (circles the room centre looking outward, a full turn per period:
            rotation-dominant), "translate" (slides sideways in front of a wall with little
            rotation: translation-dominant), "loop" (an ellipse through the room that returns
            to its start every period: for loop closure), "handheld" (a slow pan with
            hand-held shake).
        period: duration of one cycle of the trajectory, seconds (default 10 s = 300 frames at
            30 Hz, so the default "loop" closes at its last frame).
        fx, fy, cx, cy: intrinsics in pixels; None takes TUM freiburg1's scaled to the size.
        depth_noise: apply the Kinect-like noise model to depth.
        depth_noise_k: k in sigma_z = k z^2, 1/m (Kinect v1: about 0.0012 to 0.0019).
        depth_holes: fraction of pixels whose depth is dropped (set to 0) at random.
        depth_scale: depth quantisation, steps per metre (TUM: 5000, i.e. 0.2 mm steps); also
            the scale of the 16-bit depth PNGs ``write_tum_folder`` writes.
        max_depth: depth beyond this is invalid (0), metres.
        imu_rate: IMU sample rate, Hz.
        gyro_noise_density: rad/s/sqrt(Hz).
        gyro_bias_walk: rad/s^2/sqrt(Hz).
        accel_noise_density: m/s^2/sqrt(Hz).
        accel_bias_walk: m/s^3/sqrt(Hz).
        gyro_bias_init: standard deviation of the initial gyroscope bias, rad/s.
        accel_bias_init: standard deviation of the initial accelerometer bias, m/s^2.
        gravity: magnitude of gravity, m/s^2 (pointing to world -z).
        attitude_time_constant: tilt-correction time constant of the attitude filter, seconds.
        texture_density: texels per metre of the surface textures.
        batch_size: frames rendered together when iterating or writing.
    """

    frames: int = 300
    width: int = 640
    height: int = 480
    fps: float = 30.0
    seed: int = 0
    trajectory: str = "orbit"
    period: float = 10.0
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    depth_noise: bool = True
    depth_noise_k: float = 0.0015
    depth_holes: float = 0.01
    depth_scale: float = 5000.0
    max_depth: float = 10.0
    imu_rate: float = 200.0
    # The IMU noise defaults are ImuNoise's, so the two cannot drift apart.
    gyro_noise_density: float = ImuNoise.gyro_noise_density
    gyro_bias_walk: float = ImuNoise.gyro_bias_walk
    accel_noise_density: float = ImuNoise.accel_noise_density
    accel_bias_walk: float = ImuNoise.accel_bias_walk
    gyro_bias_init: float = ImuNoise.gyro_bias_init
    accel_bias_init: float = ImuNoise.accel_bias_init
    gravity: float = 9.81
    attitude_time_constant: float = 10.0
    texture_density: float = 128.0
    batch_size: int = 8

    LIMITS: ClassVar[dict[str, Limit]] = {
        "frames": AT_LEAST_1, "width": AT_LEAST_1, "height": AT_LEAST_1, "fps": POSITIVE, "seed": Limit(),
        "period": POSITIVE, "fx": POSITIVE, "fy": POSITIVE, "cx": Limit(), "cy": Limit(), "depth_noise_k": NON_NEGATIVE,
        "depth_holes": Limit(ge=0, lt=1), "depth_scale": Limit(ge=DEPTH_SCALE_RANGE[0], le=DEPTH_SCALE_RANGE[1]),
        "max_depth": POSITIVE, "imu_rate": POSITIVE, "gyro_noise_density": NON_NEGATIVE, "gyro_bias_walk": NON_NEGATIVE,
        "accel_noise_density": NON_NEGATIVE, "accel_bias_walk": NON_NEGATIVE, "gyro_bias_init": NON_NEGATIVE,
        "accel_bias_init": NON_NEGATIVE, "gravity": POSITIVE, "attitude_time_constant": Limit(gt=0, allow_inf=True),
        "texture_density": Limit(gt=0, le=1024), "batch_size": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        def fail(key: str, expected: str) -> None:
            raise ConfigError(f"SyntheticConfig.{key}: expected {expected}, got {getattr(self, key)!r}")

        check_limits(self)
        if self.trajectory not in SYNTHETIC_TRAJECTORIES:
            fail("trajectory", "one of " + ", ".join(repr(t) for t in SYNTHETIC_TRAJECTORIES))
        if not isinstance(self.depth_noise, bool):
            fail("depth_noise", "true or false")
        if self.max_depth * self.depth_scale > 65535:
            fail("max_depth", f"at most {65535 / self.depth_scale:.3f} m so depth fits 16-bit PNGs at depth_scale")
        # The same plausibility test as a calibration.txt (calibration.intrinsics_problem).
        cam = camera_from_config(self)
        problem = intrinsics_problem(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, self.depth_scale)
        if problem is not None:
            raise FieldError(*problem, owner=type(self).__name__)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """Return the names of all settings."""
        return tuple(f.name for f in fields(cls))

    def imu_noise(self) -> ImuNoise:
        """Return the IMU noise model of these settings."""
        return ImuNoise(
            gyro_noise_density=self.gyro_noise_density,
            gyro_bias_walk=self.gyro_bias_walk,
            accel_noise_density=self.accel_noise_density,
            accel_bias_walk=self.accel_bias_walk,
            gyro_bias_init=self.gyro_bias_init,
            accel_bias_init=self.accel_bias_init,
        )


def camera_from_config(cfg: SyntheticConfig) -> PinholeCamera:
    """Return the camera of ``cfg``: explicit intrinsics, or TUM freiburg1's scaled to the image size."""
    fx0, fy0, cx0, cy0, w0, h0 = _FR1
    sx, sy = cfg.width / w0, cfg.height / h0
    # Pixel centres sit at integers, so scale about the image edge at -0.5.
    return PinholeCamera(
        fx=float(cfg.fx) if cfg.fx is not None else fx0 * sx,
        fy=float(cfg.fy) if cfg.fy is not None else fy0 * sy,
        cx=float(cfg.cx) if cfg.cx is not None else (cx0 + 0.5) * sx - 0.5,
        cy=float(cfg.cy) if cfg.cy is not None else (cy0 + 0.5) * sy - 0.5,
        width=cfg.width,
        height=cfg.height,
    )


def _sub_seed(seed: int, stream: int, index: int = 0) -> int:
    """Derive independent, order-free seeds for the scene, shake, IMU and each frame's noise."""
    x = (seed * 0x9E3779B97F4A7C15 + stream * 0xBF58476D1CE4E5B9 + index * 0x94D049BB133111EB) % (2**64)
    x ^= x >> 31
    return x % (2**63)


def _generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    gen = torch.Generator(device=device)
    gen.manual_seed(seed)
    return gen


# --------------------------------------------------------------------------------------------
# Scene


@dataclass(frozen=True)
class Scene:
    """Analytic primitives, the rectangles that bound them, and their textures.

    Boxes are the primitives: box 0 is the room, seen from inside; a flat panel is a box with a
    zero half extent on its normal axis. Faces are what the renderer intersects: the six sides of
    a box, or the front and back of a flat panel, each a rectangle with its own texture.

    Convention:
        A face is visible from a point on the side its ``face_normal`` points to (into the room
        for the room's faces). Its texel ``(col, row)`` at a surface point X is
        ``(((X - c) . u + h_u) rho, ((X - c) . v + h_v) rho)`` with ``rho`` = ``texel_density``.

    Attributes:
        centers: (K, 3) float64 box centres in the world, metres.
        R_wo: (K, 3, 3) float64 box-to-world rotations.
        half: (K, 3) float64 box half extents, metres.
        face_center: (F, 3) float64 face centres, metres.
        face_normal: (F, 3) float64 unit normals on the visible side.
        face_u, face_v: (F, 3) float64 unit in-plane axes.
        face_half: (F, 2) float64 half sizes along u and v, metres.
        face_prim: (F,) int64 box of each face.
        face_offset: (F,) int64 first texel of each face in ``atlas``.
        face_width, face_height: (F,) int64 texture columns and rows (>= 2).
        atlas: (T, 3) float32 RGB texels in [0, 1], row-major per face.
        texel_density: texels per metre.
    """

    centers: Tensor
    R_wo: Tensor
    half: Tensor
    face_center: Tensor
    face_normal: Tensor
    face_u: Tensor
    face_v: Tensor
    face_half: Tensor
    face_prim: Tensor
    face_offset: Tensor
    face_width: Tensor
    face_height: Tensor
    atlas: Tensor
    texel_density: float

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    def to(self, device: torch.device | str) -> "Scene":
        """Return the scene with every tensor on ``device``."""
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        return Scene(**{k: v.to(device) if isinstance(v, Tensor) else v for k, v in moved.items()})

    def surface_distance(self, points_w: Tensor, prim: Tensor | None = None) -> Tensor:
        """Distance of world points to box surfaces, metres.

        Args:
            points_w: (N, 3) world points.
            prim: (N,) int64 box index of each point, or None for the nearest surface of all.

        Returns:
            (N,) float64 distances.
        """
        check_shape(points_w, "N 3", "points_w")
        p = points_w.to(torch.float64)
        R, c, h = self.R_wo.to(p.device), self.centers.to(p.device), self.half.to(p.device)
        local = torch.einsum("kji,nkj->nki", R, p[:, None, :] - c[None])  # (N, K, 3)
        q = local.abs() - h
        outside = q.clamp_min(0).norm(dim=-1)
        inside = q.amax(-1).clamp_max(0)
        dist = (outside + inside).abs()  # |signed distance| to each box boundary
        if prim is None:
            return dist.amin(-1)
        return dist.gather(1, prim.to(p.device).long()[:, None])[:, 0]


def _uniform(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=torch.float64))


def _frame_from_normal(n: Tensor) -> Tensor:
    """Right-handed rotation whose local x is horizontal, y is up-ish and z is the unit normal ``n``."""
    up = n.new_tensor([0.0, 0.0, 1.0])
    x = torch.linalg.cross(up, n)
    if float(x.norm()) < 1e-9:  # horizontal panel: any horizontal x
        x = n.new_tensor([1.0, 0.0, 0.0])
    x = x / x.norm()
    y = torch.linalg.cross(n, x)
    return torch.stack([x, y, n], dim=-1)


def _yaw(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _layout(gen: torch.Generator) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Place the room and its furniture; returns (centre, R_wo, half) per primitive.

    Furniture stays within 0.85 m of the walls (or in the corners), so every trajectory, which
    keeps within 1.7 m of the room centre, has a clear path and never sees through a wall.
    """
    f64 = torch.float64
    prims = [(torch.tensor(ROOM_CENTER, dtype=f64), torch.eye(3, dtype=f64), torch.tensor(ROOM_HALF, dtype=f64))]
    walls = [((3.0, 0.0), (-1.0, 0.0)), ((-3.0, 0.0), (1.0, 0.0)), ((0.0, 3.0), (0.0, -1.0)), ((0.0, -3.0), (0.0, 1.0))]
    for (wx, wy), (nx, ny) in walls:
        n = torch.tensor([nx, ny, 0.0], dtype=f64)  # inward normal
        a = torch.tensor([-ny, nx, 0.0], dtype=f64)  # along the wall
        wall = torch.tensor([wx, wy, 0.0], dtype=f64)
        base_yaw = math.atan2(ny, nx)
        s = -2.05 + _uniform(gen, 0.0, 0.4)
        while True:
            width, depth, height = _uniform(gen, 0.4, 1.0), _uniform(gen, 0.3, 0.6), _uniform(gen, 0.35, 1.6)
            yaw = _uniform(gen, -0.3, 0.3)
            gap = _uniform(gen, 0.03, 0.15)
            ext_n = 0.5 * depth * abs(math.cos(yaw)) + 0.5 * width * abs(math.sin(yaw))
            ext_a = 0.5 * width * abs(math.cos(yaw)) + 0.5 * depth * abs(math.sin(yaw))
            if gap + 2 * ext_n > 0.8:
                depth *= 0.8 / (gap + 2 * ext_n)
                ext_n = 0.5 * depth * abs(math.cos(yaw)) + 0.5 * width * abs(math.sin(yaw))
            if s + 2 * ext_a > 2.05:
                break
            if _uniform(gen, 0.0, 1.0) < 0.85:
                centre = wall + n * (gap + ext_n) + a * (s + ext_a)
                centre[2] = 0.5 * height
                R = _yaw(base_yaw + yaw)
                prims.append((centre, R, torch.tensor([0.5 * depth, 0.5 * width, 0.5 * height], dtype=f64)))
                if _uniform(gen, 0.0, 1.0) < 0.35 and height < 1.2:
                    # A smaller box standing on this one.
                    w2, d2, h2 = 0.6 * width * _uniform(gen, 0.6, 1.0), 0.6 * depth * _uniform(gen, 0.6, 1.0), _uniform(gen, 0.15, 0.45)
                    top = centre.clone()
                    top[2] = height + 0.5 * h2
                    prims.append((top, _yaw(base_yaw + yaw + _uniform(gen, -0.4, 0.4)), torch.tensor([0.5 * d2, 0.5 * w2, 0.5 * h2], dtype=f64)))
            s += 2 * ext_a + _uniform(gen, 0.05, 0.5)
        for _ in range(2):
            # Posters: flat panels 1 cm off the wall.
            pw, ph = _uniform(gen, 0.5, 1.2), _uniform(gen, 0.4, 0.8)
            centre = wall + n * 0.01 + a * _uniform(gen, -2.2, 2.2)
            centre[2] = _uniform(gen, 1.3, 2.3)
            prims.append((centre, _frame_from_normal(n), torch.tensor([0.5 * pw, 0.5 * ph, 0.0], dtype=f64)))
    for cx, cy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        if _uniform(gen, 0.0, 1.0) < 0.75:
            # Free-standing panel in the corner, facing the room and leaning back.
            pw, ph = _uniform(gen, 0.6, 0.9), _uniform(gen, 1.0, 1.5)
            n = torch.tensor([-cx, -cy, 0.0], dtype=f64) / math.sqrt(2)
            lean = _uniform(gen, 0.1, 0.3)
            R = _frame_from_normal(n)
            x = R[:, 0]
            R = so3_exp(x * lean) @ R  # rotate about the panel's horizontal axis: the top leans back
            centre = torch.tensor([2.5 * cx, 2.5 * cy, 0.5 * ph * math.cos(lean) + 0.05], dtype=f64)
            prims.append((centre, R, torch.tensor([0.5 * pw, 0.5 * ph, 0.0], dtype=f64)))
    # A rug on the floor.
    rug = torch.tensor([_uniform(gen, -0.5, 0.5), _uniform(gen, -0.5, 0.5), 0.004], dtype=f64)
    prims.append((rug, _yaw(_uniform(gen, 0.0, math.pi)), torch.tensor([0.8, 0.6, 0.0], dtype=f64)))
    return prims


def _value_noise(h: int, w: int, cell: float, gen: torch.Generator) -> Tensor:
    """(h, w) smooth noise in [0, 1] with feature size ``cell`` texels (bicubic-interpolated lattice)."""
    cell_i = max(1, int(round(cell)))
    gh, gw = h // cell_i + 3, w // cell_i + 3
    grid = torch.rand(1, 1, gh, gw, generator=gen)
    up = F.interpolate(grid, size=((gh - 1) * cell_i + 1, (gw - 1) * cell_i + 1), mode="bicubic", align_corners=True)
    oy, ox = int(torch.randint(0, cell_i, (), generator=gen)), int(torch.randint(0, cell_i, (), generator=gen))
    return up[0, 0, oy : oy + h, ox : ox + w].clamp(0, 1)


def _face_texture(h: int, w: int, rho: float, gen: torch.Generator, shade: float) -> Tensor:
    """(3, h, w) texture of one face with mixed random patterns; ``rho`` texels per metre."""
    dark = torch.rand(3, generator=gen) * 0.35
    light = 0.55 + torch.rand(3, generator=gen) * 0.45
    c2, c3 = torch.rand(3, generator=gen), torch.rand(3, generator=gen)
    n_large = _value_noise(h, w, 0.45 * rho, gen)
    n_mid = _value_noise(h, w, 0.12 * rho, gen)
    n_fine = _value_noise(h, w, 0.03 * rho, gen)
    base = 0.5 * n_large + 0.3 * n_mid + 0.2 * n_fine
    col = dark[:, None, None] + (light - dark)[:, None, None] * base
    blobs = _value_noise(h, w, _uniform(gen, 0.06, 0.2) * rho, gen) > 0.62
    col = torch.where(blobs, c2[:, None, None] * (0.7 + 0.3 * n_fine), col)
    style = int(torch.randint(0, 3, (), generator=gen))
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    if style == 0:
        cell = _uniform(gen, 0.05, 0.15) * rho
        checker = ((torch.floor(xx / cell) + torch.floor(yy / cell)) % 2 == 1) & (n_large > 0.45)
        col = torch.where(checker, col * 0.4, col)
    elif style == 1:
        count = min(150, max(4, int(6 * (h * w) / (rho * rho))))
        for _ in range(count):
            rw = max(2, int(_uniform(gen, 0.03, 0.25) * rho))
            rh = max(2, int(_uniform(gen, 0.03, 0.25) * rho))
            x0 = int(torch.randint(0, max(1, w - rw), (), generator=gen))
            y0 = int(torch.randint(0, max(1, h - rh), (), generator=gen))
            colour = c3 * _uniform(gen, 0.3, 1.0) if _uniform(gen, 0, 1) < 0.5 else torch.rand(3, generator=gen)
            col[:, y0 : y0 + rh, x0 : x0 + rw] = colour[:, None, None]
    else:
        period = _uniform(gen, 0.04, 0.12) * rho
        angle = _uniform(gen, 0.0, math.pi)
        phase = (xx * math.cos(angle) + yy * math.sin(angle)) / period
        stripes = (torch.frac(phase) < 0.5) & (n_mid > 0.5)
        col = torch.where(stripes, c3[:, None, None] * 0.8 + 0.1, col)
    col = col + (torch.rand(1, h, w, generator=gen) - 0.5) * 0.08
    return (col * shade).clamp(0, 1)


def build_scene(seed: int = 0, texture_density: float = 128.0, device: torch.device | str | None = None) -> Scene:
    """Lay out and texture the synthetic room, deterministically from ``seed``.

    Args:
        seed: layout and texture seed.
        texture_density: texels per metre.
        device: where the scene's tensors live (CPU if None).

    Returns:
        The scene; box 0 is the room.
    """
    gen = _generator(_sub_seed(seed, 1))
    prims = _layout(gen)
    centers = torch.stack([p[0] for p in prims])
    R_wo = torch.stack([p[1] for p in prims])
    half = torch.stack([p[2] for p in prims])
    light = torch.tensor(_LIGHT, dtype=torch.float64)
    light = light / light.norm()
    rows: list[tuple] = []
    textures = []
    for k in range(len(prims)):
        for axis in range(3):
            u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
            hu, hv = float(half[k, u_ax]), float(half[k, v_ax])
            if hu <= 0 or hv <= 0:
                continue  # the zero-area rims of a flat panel
            w = int(math.ceil(2 * hu * texture_density)) + 2
            h = int(math.ceil(2 * hv * texture_density)) + 2
            for side in (-1.0, 1.0):
                outward = side * R_wo[k, :, axis]
                centre = centers[k] + side * half[k, axis] * R_wo[k, :, axis]
                normal = -outward if k == 0 else outward  # the room is seen from inside
                shade = 0.55 + 0.45 * max(0.0, float(normal @ light))
                tex = _face_texture(h, w, texture_density, gen, shade)
                textures.append(tex.permute(1, 2, 0).reshape(-1, 3))
                rows.append((centre, normal, R_wo[k, :, u_ax], R_wo[k, :, v_ax], torch.tensor([hu, hv], dtype=torch.float64), k, w, h))
    sizes = torch.tensor([t.shape[0] for t in textures], dtype=torch.int64)
    scene = Scene(
        centers=centers,
        R_wo=R_wo,
        half=half,
        face_center=torch.stack([r[0] for r in rows]),
        face_normal=torch.stack([r[1] for r in rows]),
        face_u=torch.stack([r[2] for r in rows]),
        face_v=torch.stack([r[3] for r in rows]),
        face_half=torch.stack([r[4] for r in rows]),
        face_prim=torch.tensor([r[5] for r in rows], dtype=torch.int64),
        face_offset=torch.cumsum(sizes, 0) - sizes,
        face_width=torch.tensor([r[6] for r in rows], dtype=torch.int64),
        face_height=torch.tensor([r[7] for r in rows], dtype=torch.int64),
        atlas=torch.cat(textures).contiguous(),
        texel_density=float(texture_density),
    )
    return scene if device is None else scene.to(device)


# --------------------------------------------------------------------------------------------
# Rendering


@dataclass(frozen=True)
class RenderOutput:
    """Rendered images.

    Attributes:
        rgb: (B, 3, H, W) float32 colour in [0, 1].
        depth: (B, 1, H, W) float32 depth along the optical axis, metres (0 where nothing is hit).
        prim: (B, H, W) int64 index of the primitive seen at each pixel (-1 where nothing is hit).
    """

    rgb: Tensor
    depth: Tensor
    prim: Tensor


class SceneRenderer:
    """Batched ray caster of a :class:`Scene` for one pinhole camera.

    Every face is a textured rectangle. For each frame and visible face (the camera on its
    visible side) the near-plane-clipped projection of its corners gives the screen tiles it can
    cover; each overlapping (frame, tile, face) triple intersects the tile's 256 rays with the
    face's plane (``t = -n.(o - c) / n.d``), tests the hit against the rectangle and computes
    its texel address. All per-pixel arithmetic runs on tensors whose contiguous last dimension
    is the pixel, with per-(frame, face) constants broadcast along it (torch's element-wise
    kernels vectorise only that way; ``torch.where`` and reductions over a middle dimension are
    avoided for the same reason). Candidates of a tile are written to slots of a (slot, tile,
    pixel) depth buffer; a min over slots picks the nearest, its slot is recovered by equality,
    and the winner's texel address is gathered and the atlas sampled bilinearly.

    Args:
        scene: the primitives and textures.
        camera: intrinsics and image size.
        device: where rendering runs (the scene's device if None).
        tile: screen tile size in pixels used for culling.
        chunk: frames processed together inside :meth:`render`; bounds the scratch memory,
            which is kept between calls (about 75 MB per 640 x 480 frame of a chunk).

    Not safe to share between threads for one call; each thread gets its own scratch memory.
    """

    _NEAR = 1e-3  # smallest accepted depth, metres
    _MISS = 1e30  # depth given to candidate rays that miss their face

    def __init__(
        self,
        scene: Scene,
        camera: PinholeCamera,
        device: torch.device | str | None = None,
        tile: int = _TILE,
        chunk: int = 2,
    ):
        if tile < 1 or chunk < 1:
            raise ConfigError(f"tile, chunk: expected integers >= 1, got {tile} and {chunk}")
        device = torch.device(device) if device is not None else scene.atlas.device
        self.scene = scene.to(device)
        self.camera = camera
        self.device = device
        self.tile = tile
        self.chunk = chunk
        self.tiles_y = -(-camera.height // tile)
        self.tiles_x = -(-camera.width // tile)
        f32, f64 = torch.float32, torch.float64
        iy, ix = torch.meshgrid(torch.arange(tile), torch.arange(tile), indexing="ij")
        ty, tx = torch.meshgrid(torch.arange(self.tiles_y), torch.arange(self.tiles_x), indexing="ij")
        u = (tx.reshape(-1, 1) * tile + ix.reshape(1, -1)).to(f64)  # (T, S2)
        v = (ty.reshape(-1, 1) * tile + iy.reshape(1, -1)).to(f64)
        # Ray directions (rx, ry, 1) in tile order, (T, S2) each.
        self._rx = ((u - camera.cx) / camera.fx).to(f32).to(device)
        self._ry = ((v - camera.cy) / camera.fy).to(f32).to(device)
        sc = self.scene
        if sc.atlas.shape[0] >= 2**24:
            raise ConfigError(f"texture_density: an atlas of {sc.atlas.shape[0]} texels exceeds float32 texel addressing (2^24)")
        hu, hv = sc.face_half[:, 0:1], sc.face_half[:, 1:2]
        su = torch.tensor([-1.0, 1.0, 1.0, -1.0], dtype=f64, device=device)[None, :, None]
        sv = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=f64, device=device)[None, :, None]
        # Face corners in polygon order: (F, 4, 3).
        self._corners_w = sc.face_center[:, None] + su * hu[:, None] * sc.face_u[:, None] + sv * hv[:, None] * sc.face_v[:, None]
        rho = sc.texel_density
        width = sc.face_width.to(f32)
        # Per face: extent in texels along u and v, texture width, width - 1, width - 2, height - 1, height - 2, offset.
        self._face_tex = torch.stack(
            [
                (2 * rho * sc.face_half[:, 0]).to(f32),
                (2 * rho * sc.face_half[:, 1]).to(f32),
                width,
                width - 1,
                width - 2,
                sc.face_height.to(f32) - 1,
                sc.face_height.to(f32) - 2,
                sc.face_offset.to(f32),
            ],
            dim=1,
        )  # (F, 8)
        self._channels = sc.atlas.T.contiguous()  # (3, T): one flat table per channel
        self._lane = torch.arange(tile * tile, device=device)  # pixel index inside a tile
        self._local = threading.local()  # per-thread scratch memory, see _render_chunk

    def __call__(self, T_wc: Tensor) -> RenderOutput:
        return self.render(T_wc)

    def _tiles(self, R_wc: Tensor, t_wc: Tensor, visible: Tensor) -> Tensor:
        """(B, TY, TX, F) bool: tiles each visible face's clipped projection may cover."""
        cam, S, eps = self.camera, self.tile, 1e-3
        X = (self._corners_w[None] - t_wc[:, None, None, :]) @ R_wc[:, None]  # (B, F, 4, 3) camera frame
        Xn = X.roll(-1, dims=2)
        z, zn = X[..., 2], Xn[..., 2]
        # Near-plane clipping: the clipped polygon's vertices are the corners in front of the
        # plane z = eps and the edge crossings of that plane.
        crossing = (z - eps) * (zn - eps) < 0
        alpha = ((eps - z) / torch.where(crossing, zn - z, torch.ones_like(z)))[..., None]
        pts = torch.cat([X, X + alpha * (Xn - X)], dim=2)  # (B, F, 8, 3)
        ok = torch.cat([z > eps, crossing], dim=2)
        zs = pts[..., 2].clamp_min(eps)
        u = cam.fx * pts[..., 0] / zs + cam.cx
        v = cam.fy * pts[..., 1] / zs + cam.cy
        inf = torch.full_like(u, math.inf)
        umin, umax = torch.where(ok, u, inf).amin(-1), torch.where(ok, u, -inf).amax(-1)
        vmin, vmax = torch.where(ok, v, inf).amin(-1), torch.where(ok, v, -inf).amax(-1)
        visible = visible & ok.any(-1) & (umax >= 0) & (umin <= cam.width - 1) & (vmax >= 0) & (vmin <= cam.height - 1)
        tx0 = (umin.clamp(0, cam.width - 1) / S).floor().long()
        tx1 = (umax.clamp(0, cam.width - 1) / S).floor().long()
        ty0 = (vmin.clamp(0, cam.height - 1) / S).floor().long()
        ty1 = (vmax.clamp(0, cam.height - 1) / S).floor().long()
        ty = torch.arange(self.tiles_y, device=self.device)[None, :, None, None]
        tx = torch.arange(self.tiles_x, device=self.device)[None, None, :, None]
        return (
            visible[:, None, None, :]
            & (ty >= ty0[:, None, None, :]) & (ty <= ty1[:, None, None, :])
            & (tx >= tx0[:, None, None, :]) & (tx <= tx1[:, None, None, :])
        )

    def render(self, T_wc: Tensor) -> RenderOutput:
        """Render colour, depth and primitive index for camera poses.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses (set-up runs in float64, pixels in float32).

        Returns:
            Images of the batch, on the renderer's device.
        """
        check_shape(T_wc, "B 4 4", "T_wc")
        T = T_wc.to(device=self.device, dtype=torch.float64)
        B, H, W = T.shape[0], self.camera.height, self.camera.width
        out = RenderOutput(
            torch.empty(B, 3, H, W, dtype=torch.float32, device=self.device),
            torch.empty(B, 1, H, W, dtype=torch.float32, device=self.device),
            torch.empty(B, H, W, dtype=torch.int64, device=self.device),
        )
        for i in range(0, B, self.chunk):
            j = min(B, i + self.chunk)
            self._render_chunk(T[i:j], out.rgb[i:j], out.depth[i:j, 0], out.prim[i:j])
        return out

    def _render_chunk(self, T: Tensor, rgb_out: Tensor, depth_out: Tensor, prim_out: Tensor) -> None:
        """Render frames ``T`` (b, 4, 4) into the (b, 3, H, W), (b, H, W) and (b, H, W) outputs."""
        sc, cam, S, dev = self.scene, self.camera, self.tile, self.device
        f32, i64 = torch.float32, torch.int64
        B = T.shape[0]
        TY, TX = self.tiles_y, self.tiles_x
        NT, S2 = TY * TX, S * S
        G = B * NT
        R_wc, t_wc = T[:, :3, :3], T[:, :3, 3]
        rho = sc.texel_density
        # Per (frame, face) constants, float64 then float32: (B, F, ...).
        rel = t_wc[:, None, :] - sc.face_center[None]  # camera centre relative to the face
        side = (rel * sc.face_normal).sum(-1)  # > 0 on the visible side
        n_c = sc.face_normal @ R_wc  # (B, F, 3): normal in the camera frame
        u_c = rho * (sc.face_u @ R_wc)
        v_c = rho * (sc.face_v @ R_wc)
        a_u = ((rel * sc.face_u).sum(-1) + sc.face_half[:, 0]) * rho
        a_v = ((rel * sc.face_v).sum(-1) + sc.face_half[:, 1]) * rho
        consts = torch.cat([-side[..., None], n_c, u_c, v_c, a_u[..., None], a_v[..., None]], dim=-1).to(f32)  # (B, F, 12)

        overlap = self._tiles(R_wc, t_wc, side > 1e-9)  # (B, TY, TX, F)
        pb, pty, ptx, pf = overlap.nonzero(as_tuple=True)  # sorted by (frame, tile)
        P = pb.shape[0]

        def untile(x: Tensor) -> Tensor:
            x = x.reshape(B, TY, TX, S, S).permute(0, 1, 3, 2, 4).reshape(B, TY * S, TX * S)
            return x[:, : cam.height, : cam.width]

        if P == 0:
            rgb_out.zero_()
            depth_out.zero_()
            prim_out.fill_(-1)
            return
        # Every large intermediate lives in a per-thread workspace reused across calls: fresh
        # multi-megabyte allocations would be page-faulted in on every call (glibc returns them
        # to the system), which costs more than the arithmetic.
        ws = self._workspace()
        tile_idx = pty * TX + ptx
        c = consts[pb, pf].T.contiguous()[:, :, None]  # (12, P, 1): one column per constant
        ft = self._face_tex[pf].T.contiguous()[:, :, None]  # (8, P, 1)
        rx = torch.index_select(self._rx, 0, tile_idx, out=ws.take("rx", (P, S2), f32))  # (P, S2)
        ry = torch.index_select(self._ry, 0, tile_idx, out=ws.take("ry", (P, S2), f32))
        # Plane hit: t = -n.(o - c) / (n_c . ray); the ray parameter is the depth (unit z rays).
        t = torch.mul(c[1], rx, out=ws.take("t", (P, S2), f32)).add_(c[3]).addcmul_(c[2], ry)
        torch.div(c[0], t, out=t).clamp_(-1e6, 1e6)
        # Texel coordinates: col = A_u + t (u_c . ray), row = A_v + t (v_c . ray).
        col = torch.mul(c[4], rx, out=ws.take("col", (P, S2), f32)).add_(c[6]).addcmul_(c[5], ry).mul_(t).add_(c[10])
        row = torch.mul(c[7], rx, out=ws.take("row", (P, S2), f32)).add_(c[9]).addcmul_(c[8], ry).mul_(t).add_(c[11])
        # Inside the rectangle and in front of the camera <=> every margin >= 0.
        m1 = torch.sub(ft[0], col, out=ws.take("m1", (P, S2), f32))
        torch.minimum(m1, col, out=m1)
        m2 = torch.sub(ft[1], row, out=ws.take("m2", (P, S2), f32))
        torch.minimum(m2, row, out=m2)
        torch.minimum(m1, m2, out=m1)
        torch.sub(t, self._NEAR, out=m2)
        torch.minimum(m1, m2, out=m1)
        miss = torch.lt(m1, 0, out=ws.take("miss", (P, S2), torch.bool))
        t_hit = m2.copy_(miss).mul_(self._MISS).add_(t)  # misses move beyond everything
        # Bilinear sample positions, clamped to the face's texture: top-left texel and fractions.
        col.clamp_(min=torch.zeros_like(ft[3]), max=ft[3])
        row.clamp_(min=torch.zeros_like(ft[5]), max=ft[5])
        x0 = torch.floor(col, out=m1)
        torch.minimum(x0, ft[4], out=x0)
        y0 = torch.floor(row, out=ws.take("y0", (P, S2), f32))
        torch.minimum(y0, ft[6], out=y0)
        fx, fy = col.sub_(x0), row.sub_(y0)
        i00 = torch.mul(y0, ft[2], out=y0).add_(x0).add_(ft[7])  # flat texel index (exact below 2^24)

        # Candidates of a (frame, tile) get consecutive slots; the nearest per pixel wins.
        group = pb * NT + tile_idx
        counts = torch.bincount(group, minlength=G)
        first = torch.cumsum(counts, 0) - counts  # (G,) first pair of each group
        slot = torch.arange(P, device=dev) - first[group]
        L = int(counts.max())
        t_buf = ws.take("t_buf", (L, G, S2), f32).fill_(math.inf)
        t_buf[slot, group] = t_hit
        t_best = torch.amin(t_buf, 0, out=ws.take("t_best", (G, S2), f32))
        # Slot of the nearest candidate (the lowest slot on exact ties).
        win = ws.take("win", (G, S2), f32).zero_()
        eq = ws.take("eq", (G, S2), torch.bool)
        step = ws.take("step", (G, S2), f32)
        for layer in range(L - 1, -1, -1):
            torch.eq(t_buf[layer], t_best, out=eq)
            win.add_(torch.mul(win, -1.0, out=step).add_(layer).mul_(eq))
        win.add_(first.to(f32)[:, None]).clamp_(max=P - 1)  # pair index; empty groups miss below
        pair = ws.take("pair", (G * S2,), i64).copy_(win.reshape(-1))
        flat = torch.mul(pair.view(G, S2), S2, out=ws.take("flat", (G, S2), i64)).add_(self._lane).reshape(-1)
        i00_w = torch.index_select(i00.reshape(-1), 0, flat, out=ws.take("i00_w", (G * S2,), f32))
        fx_w = torch.index_select(fx.reshape(-1), 0, flat, out=ws.take("fx_w", (G * S2,), f32))
        fy_w = torch.index_select(fy.reshape(-1), 0, flat, out=ws.take("fy_w", (G * S2,), f32))
        width_w = torch.index_select(ft[2, :, 0], 0, pair, out=ws.take("width_w", (G * S2,), f32))
        t_best = t_best.reshape(-1).clamp_(max=self._MISS)
        hit = torch.lt(t_best, 0.5 * self._MISS, out=ws.take("hit", (G * S2,), torch.bool))
        hitf = ws.take("hitf", (G * S2,), f32).copy_(hit)
        depth_out.copy_(untile(t_best.mul_(hitf)))
        prim = torch.index_select(sc.face_prim[pf], 0, pair, out=ws.take("prim", (G * S2,), i64))
        hit_i = ws.take("hit_i", (G * S2,), i64).copy_(hit)
        prim_out.copy_(untile(prim.mul_(hit_i).add_(hit_i).sub_(1)))  # -1 where nothing is hit
        i00_l = ws.take("i00_l", (G * S2,), i64).copy_(i00_w)
        i01_l = torch.add(i00_l, 1, out=ws.take("i01_l", (G * S2,), i64))
        i10_l = torch.add(i00_l, width_w.to(i64), out=ws.take("i10_l", (G * S2,), i64))
        i11_l = torch.add(i10_l, 1, out=ws.take("i11_l", (G * S2,), i64))
        c00, c01 = ws.take("c00", (G * S2,), f32), ws.take("c01", (G * S2,), f32)
        c10, c11 = ws.take("c10", (G * S2,), f32), ws.take("c11", (G * S2,), f32)
        # Bilinear texel fetch from one flat table per channel.
        for k, channel in enumerate(self._channels):
            torch.index_select(channel, 0, i00_l, out=c00)
            torch.index_select(channel, 0, i01_l, out=c01)
            torch.index_select(channel, 0, i10_l, out=c10)
            torch.index_select(channel, 0, i11_l, out=c11)
            top = c01.sub_(c00).mul_(fx_w).add_(c00)
            bottom = c11.sub_(c10).mul_(fx_w).add_(c10)
            rgb_out[:, k] = untile(bottom.sub_(top).mul_(fy_w).add_(top).mul_(hitf))

    def _workspace(self) -> "_Workspace":
        ws = getattr(self._local, "workspace", None)
        if ws is None:
            ws = self._local.workspace = _Workspace(self.device)
        return ws


class _Workspace:
    """Named scratch tensors that grow to the largest size requested and are then reused."""

    def __init__(self, device: torch.device):
        self.device = device
        self._store: dict[str, Tensor] = {}

    def take(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
        """Return an uninitialised contiguous tensor of ``shape`` and ``dtype`` backed by the buffer ``name``."""
        numel = math.prod(shape)
        buf = self._store.get(name)
        if buf is None or buf.dtype != dtype or buf.numel() < numel:
            buf = torch.empty(int(numel * 1.25) + 1024, dtype=dtype, device=self.device)
            self._store[name] = buf
        return buf[:numel].view(shape)


def kinect_depth_noise(
    depth: Tensor,
    k: float = 0.0015,
    holes: float = 0.01,
    depth_scale: float = 5000.0,
    generator: torch.Generator | None = None,
    max_depth: float = math.inf,
) -> Tensor:
    """Apply a Kinect-like noise model to exact depth.

    ``z' = round((z + k z^2 n) depth_scale) / depth_scale`` with ``n ~ N(0, 1)``; a random
    fraction ``holes`` of pixels, and depth beyond ``max_depth`` or not positive, become 0.

    Args:
        depth: (..., H, W) exact depth, metres (0 = invalid).
        k: noise coefficient, 1/m (sigma_z = k z^2).
        holes: fraction of pixels dropped.
        depth_scale: quantisation steps per metre (0: no quantisation).
        generator: random source (a fresh default generator if None).
        max_depth: range limit, metres.

    Returns:
        Noisy depth, same shape, dtype and device.
    """
    check_float(depth, "depth")
    if not (math.isfinite(k) and k >= 0):
        raise ConfigError(f"k: expected a noise coefficient >= 0 in 1/m, got {k!r}")
    if not 0 <= holes < 1:
        raise ConfigError(f"holes: expected a fraction in [0, 1), got {holes!r}")
    if not (math.isfinite(depth_scale) and depth_scale >= 0):
        raise ConfigError(f"depth_scale: expected steps per metre >= 0 (0: none), got {depth_scale!r}")
    valid = depth > 0
    n = torch.randn(depth.shape, generator=generator, dtype=depth.dtype, device=depth.device)
    drop = torch.rand(depth.shape, generator=generator, dtype=depth.dtype, device=depth.device) < holes
    z = depth + k * depth * depth * n
    if depth_scale > 0:
        z = torch.round(z * depth_scale) / depth_scale
    keep = valid & ~drop & (z > 0) & (z <= max_depth)
    return torch.where(keep, z, torch.zeros_like(z))


# --------------------------------------------------------------------------------------------
# Trajectories and IMU


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


def synthetic_trajectory(cfg: SyntheticConfig) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """Return the analytic camera motion of ``cfg`` as a function of time.

    The function maps (M,) float64 times (seconds) to ``R_wc`` (M, 3, 3) and camera centres
    (M, 3) in metres; it is smooth and built from differentiable torch operations, so velocities
    and accelerations follow by automatic differentiation.
    """
    kind, period = cfg.trajectory, float(cfg.period)
    gen = _generator(_sub_seed(cfg.seed, 2))
    shake_t, shake_r = _shake(gen, 8, 0.012), _shake(gen, 8, 0.008)

    def pose(t: Tensor) -> tuple[Tensor, Tensor]:
        th = 2 * math.pi * t / period
        s, c = torch.sin(th), torch.cos(th)
        if kind == "orbit":
            p = torch.stack([0.6 * c, 0.6 * s, 1.4 + 0.1 * torch.sin(2 * th)], -1)
            look = torch.stack([torch.cos(th + 0.3), torch.sin(th + 0.3), -0.25 + 0.1 * torch.sin(3 * th)], -1)
            return _look_at(p, p + look), p
        if kind == "translate":
            p = torch.stack([1.0 * s, -1.2 + 0.15 * torch.sin(2 * th), 1.3 + 0.2 * torch.sin(2 * th + 1.0)], -1)
            look = torch.stack([0.1 * s, -torch.ones_like(s), -0.35 + 0.05 * c], -1)
            return _look_at(p, p + look), p
        if kind == "loop":
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


def synthetic_kinematics(cfg: SyntheticConfig, times: Tensor) -> Kinematics:
    """Exact motion of the synthetic camera (= IMU) at ``times``.

    Acceleration and the rotation derivative come from automatic differentiation of the
    analytic trajectory (:func:`torchslam.imu.time_derivatives`; each sample depends only on its
    own time), so ``omega_b = vex(R^T dR/dt)`` is exact.

    Args:
        cfg: the sequence settings.
        times: (M,) float64 seconds.

    Returns:
        Kinematics with world acceleration and body angular rate.
    """
    check_shape(times, "M", "times")
    pose = synthetic_trajectory(cfg)
    t = times.to(torch.float64)
    _, _, accel = time_derivatives(lambda x: pose(x)[1], t, 2)
    R, R_dot = time_derivatives(lambda x: pose(x)[0], t, 1)
    omega = vex(R.transpose(-1, -2) @ R_dot)
    return Kinematics(t, R, omega, accel)


# --------------------------------------------------------------------------------------------
# Sequence


class SyntheticSequence(Sequence):
    """A synthetic RGB-D-inertial sequence (implements the ``Sequence`` protocol).

    Frames are rendered lazily: indexing renders the batch of ``cfg.batch_size`` frames holding
    the index and keeps it, so sequential access runs at batched speed; iteration renders batch
    by batch. Depth noise of frame i is drawn from a generator seeded by (seed, i), so a frame is
    the same however it was reached.

    Attributes:
        name: "synthetic-<trajectory>-seed<seed>".
        camera: intrinsics and size.
        timestamps: (N,) float64 frame times ``k / fps``, seconds.
        groundtruth: exact camera-to-world poses at the frame times.
        imu: simulated IMU stream (IMU frame = camera frame) from t = 0 to (at least) the last frame.
        imu_gyro_bias, imu_accel_bias: (M, 3) float64 true biases of that stream.
        attitude: AHRS attitude from ``imu`` (source "imu"), started at the true first attitude.
        scene: the rendered scene.
        gravity_w: (3,) float64 gravity in the world frame, m/s^2.
    """

    def __init__(self, cfg: SyntheticConfig | None = None, device: torch.device | str | None = None):
        cfg = SyntheticConfig() if cfg is None else cfg
        self.cfg = cfg
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.name = f"synthetic-{cfg.trajectory}-seed{cfg.seed}"
        self.camera = camera_from_config(cfg)
        self.timestamps = torch.arange(cfg.frames, dtype=torch.float64) / cfg.fps
        pose = synthetic_trajectory(cfg)
        R, p = pose(self.timestamps)
        self.groundtruth = Trajectory(self.timestamps, se3_from_Rt(R, p))
        self.gravity_w = torch.tensor([0.0, 0.0, -cfg.gravity], dtype=torch.float64)
        t_end = float(self.timestamps[-1])
        # IMU samples k / imu_rate from 0 up to the first sample at or after the last frame.
        imu_times = torch.arange(int(math.ceil(t_end * cfg.imu_rate - 1e-9)) + 1, dtype=torch.float64) / cfg.imu_rate
        sim = simulate_imu(synthetic_kinematics(cfg, imu_times), cfg.imu_noise(), self.gravity_w, _sub_seed(cfg.seed, 3))
        self.imu: ImuData = sim.imu
        self.imu_gyro_bias, self.imu_accel_bias = sim.gyro_bias, sim.accel_bias
        self.attitude: AttitudeStream = ahrs_attitude(
            self.imu, R[0], time_constant=cfg.attitude_time_constant, gravity=cfg.gravity
        )
        self.scene = build_scene(cfg.seed, cfg.texture_density, self.device)
        self.renderer = SceneRenderer(self.scene, self.camera, self.device)
        self._cached: tuple[int, Tensor, Tensor] | None = None

    def __len__(self) -> int:
        return self.cfg.frames

    def render(self, indices: Tensor | list[int] | range) -> tuple[Tensor, Tensor]:
        """Render frames by index (no caching).

        Args:
            indices: (B,) frame indices.

        Returns:
            rgb: (B, 3, H, W) float32 in [0, 1]; depth: (B, 1, H, W) float32 metres, 0 = invalid
            (noisy if ``cfg.depth_noise``).
        """
        idx = torch.as_tensor(list(indices) if not isinstance(indices, Tensor) else indices, dtype=torch.int64)
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= len(self)):
            raise IndexError(f"indices: frame index out of range 0..{len(self) - 1}")
        out = self.renderer.render(self.groundtruth.T_wc[idx])
        depth = out.depth
        cfg = self.cfg
        if cfg.depth_noise:
            # One generator per frame so noise does not depend on how frames were batched.
            depth = torch.stack(
                [
                    kinect_depth_noise(
                        depth[j],
                        cfg.depth_noise_k,
                        cfg.depth_holes,
                        cfg.depth_scale,
                        _generator(_sub_seed(cfg.seed, 4, int(i)), self.device),
                        cfg.max_depth,
                    )
                    for j, i in enumerate(idx.tolist())
                ]
            ) if idx.numel() else depth
        else:
            depth = torch.where(depth <= cfg.max_depth, depth, torch.zeros_like(depth))
        return out.rgb, depth

    def _frame(self, i: int, rgb: Tensor, depth: Tensor) -> Frame:
        return Frame(index=i, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, T_wc=self.groundtruth.T_wc[i])

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"index: expected an int, got {type(index).__name__}")
        i = int(index) + n if index < 0 else int(index)
        if not 0 <= i < n:
            raise IndexError(f"index: {index} out of range for {n} frames")
        bs = self.cfg.batch_size
        start = (i // bs) * bs
        if self._cached is None or self._cached[0] != start:
            rgb, depth = self.render(range(start, min(start + bs, n)))
            self._cached = (start, rgb, depth)
        _, rgb, depth = self._cached
        # Copies, so a consumer writing into its frame cannot alter the cached batch.
        return self._frame(i, rgb[i - start].clone(), depth[i - start].clone())

    def __iter__(self) -> Iterator[Frame]:
        bs = self.cfg.batch_size
        for start in range(0, len(self), bs):
            stop = min(start + bs, len(self))
            rgb, depth = self.render(range(start, stop))
            for j in range(stop - start):
                yield self._frame(start + j, rgb[j], depth[j])


def generate_sequence(cfg: SyntheticConfig | None = None, device: torch.device | str | None = None) -> SyntheticSequence:
    """Build a synthetic sequence (scene, trajectory, IMU, attitude); frames render on access.

    Args:
        cfg: settings (defaults if None).
        device: where scene and images live (CPU if None).
    """
    return SyntheticSequence(cfg, device)


# What ``write_tum_folder`` writes, and the comment its calibration.txt (written first) starts with.
TUM_FOLDER_ENTRIES = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "calibration.txt", "imu.txt")
_CALIBRATION_MARK = "# fx fy cx cy depth_scale width height   (torchslam synthetic pinhole camera"


def _prepare_tum_folder(out: Path, overwrite: bool) -> None:
    """Make ``out`` an empty folder; with ``overwrite`` clear a folder that ``write_tum_folder`` wrote.

    A folder "looks written by torchslam" when it holds nothing but ``TUM_FOLDER_ENTRIES``, its
    ``rgb/`` and ``depth/`` hold only PNG files, and its ``calibration.txt`` (the first file the
    writer writes, so an interrupted write is recognised too) carries the writer's comment.
    Anything else is refused rather than deleted.
    """
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if not out.is_dir():
        return
    entries = sorted(out.iterdir())
    if not entries:
        return
    if not overwrite:
        raise ConfigError(
            f"{out}: folder is not empty ({len(entries)} entries); pass --overwrite (overwrite=True) to replace "
            "a sequence that torchslam synth wrote there, or choose a new folder"
        )
    foreign = [p.name for p in entries if p.name not in TUM_FOLDER_ENTRIES]
    foreign += [
        f"{sub}/{p.name}" for sub in ("rgb", "depth") if (out / sub).is_dir()
        for p in sorted((out / sub).iterdir()) if p.suffix != ".png" or not p.is_file()
    ]
    foreign += [name for name in ("rgb", "depth") if (out / name).exists() and not (out / name).is_dir()]
    calib = out / "calibration.txt"
    try:
        marked = calib.read_text(errors="replace").startswith(_CALIBRATION_MARK)
    except OSError:
        marked = False
    if foreign or not marked:
        why = f"it holds {', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}" if foreign else (
            "its calibration.txt was not written by torchslam synth")
        raise ConfigError(
            f"{out}: not cleared for --overwrite: {why}; only an empty folder or a sequence folder that "
            "torchslam synth wrote is replaced"
        )
    for p in entries:
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()
    logger.info("cleared %s (%d entries) to write a new sequence", out, len(entries))


def write_tum_folder(seq: SyntheticSequence, out_dir: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a synthetic sequence as a TUM RGB-D folder.

    Layout: ``rgb/<t>.png`` (8-bit colour), ``depth/<t>.png`` (16-bit, metres x depth_scale,
    0 = invalid), ``rgb.txt`` and ``depth.txt`` (``timestamp path``), ``groundtruth.txt``
    (``t tx ty tz qx qy qz qw``, camera-to-world), ``calibration.txt`` (``fx fy cx cy
    depth_scale width height``) and ``imu.txt`` (``timestamp gx gy gz ax ay az``; rad/s and
    m/s^2 in the IMU frame, which is the camera frame). Timestamps are written with 6 decimals.
    ``torchslam.data.TUMSequence`` reads all of it back, ``imu.txt`` included.

    Args:
        seq: the sequence.
        out_dir: folder to create, or an empty folder.
        overwrite: replace the contents of a non-empty ``out_dir`` if it is a sequence folder this
            function wrote (nothing but its files, see ``TUM_FOLDER_ENTRIES``); anything else is
            refused.

    Returns:
        The folder path.

    Raises:
        ConfigError: ``out_dir`` is a file, or is not empty (without ``overwrite``, or with it
            when it does not look like a folder this function wrote).
    """
    import cv2  # only the writer needs OpenCV

    out = Path(out_dir)
    _prepare_tum_folder(out, overwrite)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    cfg, cam = seq.cfg, seq.camera
    (out / "calibration.txt").write_text(
        f"{_CALIBRATION_MARK}; raw/depth_scale = metres; 0 = invalid)\n"
        f"{cam.fx:.6f} {cam.fy:.6f} {cam.cx:.6f} {cam.cy:.6f} {cfg.depth_scale:g} {cam.width} {cam.height}\n"
    )
    stamps = [f"{float(t):.6f}" for t in seq.timestamps]
    bs = cfg.batch_size
    for start in range(0, len(seq), bs):
        stop = min(start + bs, len(seq))
        rgb, depth = seq.render(range(start, stop))
        rgb8 = (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        raw = (depth[:, 0] * cfg.depth_scale).round().clamp(0, 65535).cpu().numpy().astype(np.uint16)
        for j in range(stop - start):
            name = stamps[start + j] + ".png"
            if not cv2.imwrite(str(out / "rgb" / name), np.ascontiguousarray(rgb8[j][:, :, ::-1])):
                raise OSError(f"{out / 'rgb' / name}: could not write PNG")
            if not cv2.imwrite(str(out / "depth" / name), raw[j]):
                raise OSError(f"{out / 'depth' / name}: could not write PNG")
    source = f"torchslam synthetic sequence {seq.name} ({cfg.frames} frames, {cfg.width}x{cfg.height})"
    for kind, title in (("rgb", "color images"), ("depth", "depth maps")):
        lines = [f"# {title}", f"# file: '{source}'", "# timestamp filename"]
        lines += [f"{s} {kind}/{s}.png" for s in stamps]
        (out / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    write_tum_trajectory(out / "groundtruth.txt", seq.groundtruth, header=f"ground truth trajectory\nfile: '{source}'")
    imu = seq.imu
    rows = torch.cat([imu.timestamps[:, None], imu.gyro, imu.accel], dim=1).tolist()
    lines = [
        "# imu data",
        f"# file: '{source}'",
        "# gyro rad/s, accel m/s^2 (specific force), IMU frame = camera frame (x right, y down, z forward)",
        "# world gravity (0, 0, -g): a camera at rest measures accel = R_wc^T (0, 0, g)",
        "# timestamp gx gy gz ax ay az",
    ]
    lines += [f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) for r in rows]
    (out / "imu.txt").write_text("\n".join(lines) + "\n")
    logger.info("wrote %d frames of %s to %s", len(seq), seq.name, out)
    return out
