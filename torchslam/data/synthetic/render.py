"""Batched ray casting of the synthetic room, and a Kinect-like depth noise model.

``SceneRenderer`` casts one ray per pixel for a batch of frames at once. It intersects the
boxes' faces rather than slab-testing whole boxes: for a convex box the nearest front-facing
face hit is the slab test's entry point, and a per-face intersection yields the texel address
with per-face constants instead of per-pixel face selection.

1. Camera rays ``((u - cx) / fx, (v - cy) / fy, 1)`` are precomputed in 16 x 16 tile order. With
   a unit z component the ray parameter at a hit *is* the depth along the optical axis.
2. Every face is a textured rectangle. For each frame and each face whose visible side faces
   the camera, the near-plane-clipped projection of its corners gives the screen tiles it can
   cover; only overlapping (frame, tile, face) triples are intersected, so the work follows the
   faces' screen area (about two candidates per pixel) instead of pixels x faces.
3. A candidate is a ray-plane intersection tested against the rectangle, which also yields the
   texel address; the nearest candidate per pixel wins (a min over per-tile slots), and the
   texel atlas is sampled bilinearly at the winner's address.

Depth is exact up to float32 round-off (about 1e-6 m); ``kinect_depth_noise`` applies Gaussian
noise with sigma_z = k z^2, random holes and quantisation to 1 / depth_scale m on top.

Convention:
    Camera frame: x right, y down, z forward (OpenCV); poses are camera-to-world ``T_wc``.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import torch
from torch import Tensor

from ...errors import ConfigError, check_float, check_shape
from ...geometry import PinholeCamera
from .scene import Scene

__all__ = ["RenderOutput", "SceneRenderer", "kinect_depth_noise"]

_TILE = 16


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
