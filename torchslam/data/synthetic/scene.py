"""The synthetic room: oriented boxes with procedural textures, all deterministic from a seed.

The scene is a 6 x 6 x 3 m room seen from inside, furnished with boxes along the walls (some
stacked), flat posters on the walls, free-standing tilted panels in the corners and a rug. Every
primitive is an oriented box (a flat panel is a box with one zero half-extent). Textures are
built once per face from multi-octave value noise, hard-edged blobs, checkers, stripes and
rectangles, shaded by a fixed light, and stored in one texel atlas.

Convention:
    World frame: z up; the room spans x, y in [-3, 3] m and z in [0, 3] m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor

from ...errors import check_shape
from ...geometry import so3_exp

__all__ = ["ROOM_CENTER", "ROOM_HALF", "Scene", "build_scene"]

ROOM_CENTER = (0.0, 0.0, 1.5)
ROOM_HALF = (3.0, 3.0, 1.5)
# Light direction (world) for the baked face shading.
_LIGHT = (0.35, 0.55, 1.0)


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
