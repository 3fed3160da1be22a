"""Dense RGB-D registration: photometric + geometric alignment on an image pyramid (paper §IV-A2).

GC-SLAM's dense front-end registers the current frame ``j`` to the reference keyframe ``i`` with
the dense RGB-D alignment of DVO (Kerl et al., "Robust odometry estimation for RGB-D cameras",
ICRA 2013, and "Dense visual SLAM for RGB-D cameras", IROS 2013), then keeps the pixels that
align well as correspondences for FastGO (paper §IV-A2: "correspondences are selected if their
re-projection error is less than a threshold"; 320x240, about 50,000 per pair).

Method, for B pairs at once:

1. **Working images** (:func:`prepare_dense_frame`). Colour becomes grey (ITU-R 601 weights) and
   is reduced by an integer factor ``k = max(1, round(W / DenseConfig.width))`` with a k x k box
   average (640x480 -> 320x240); depth is reduced by a *valid-aware* k x k reduction: the mean of
   the valid depths of a block, provided their spread ``max - min`` is at most
   ``depth_merge_tolerance * min``, else the block is invalid, so no depth is a mix of two
   surfaces. Depth outside ``[min_depth, max_depth]`` is invalid.
2. **Lens distortion.** A camera with distortion has its working images resampled once to an
   ideal pinhole image with the same intrinsics (grey bilinearly, depth by nearest neighbour, so
   still unmixed); everything after that is pinhole. Pixels whose source lies outside the raw
   image are invalid.
3. **Pyramid.** ``levels`` levels, finest first: grey as ``kornia.geometry.transform.pyrdown``
   (5x5 Gaussian with reflected borders, then the 2x2 average; computed as one separable 6-tap
   filter of stride 2), depth by the valid-aware 2x2 reduction, intrinsics by
   :meth:`PinholeCamera.scaled` (pixel centres at integers, so both reductions are centred on the
   scaled principal point). Image gradients are kornia's normalised Sobel, in grey levels (or
   metres) per pixel.
4. **Warp and residuals.** Each valid-depth pixel ``u`` of frame j gives ``p_j``; with the current
   ``T_ij`` it lands at ``w = pi(T_ij p_j)`` in frame i. Residuals (DVO):
   photometric ``r_I = I_i(w) - I_j(u)`` (grey in [0, 1]) and geometric
   ``r_Z = Z_i(w) - [T_ij p_j]_z`` (metres); ``I_i``, ``Z_i`` and their gradients are sampled
   bilinearly (``grid_sample``). ``r_I`` counts where ``w`` lies in ``[1, w - 2] x [1, h - 2]``
   (Sobel never sees the border) and all four bilinear neighbours come from inside the raw
   image; ``r_Z`` also needs all four neighbours to be *depth-smooth* pixels (their 3x3
   neighbourhood valid with spread at most ``depth_edge_tolerance * z``), since neither the
   interpolated depth nor its gradient means anything across a depth edge.
5. **Gauss-Newton** on SE(3) with the left update ``T_ij <- exp(delta) T_ij``. With
   ``q = T_ij p_j = (x, y, z)``, ``dq/ddelta = [I, -[q]x]`` and
   ``J_pi = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]``:
   ``J_I = grad I_i(w) J_pi dq/ddelta`` and ``J_Z = grad Z_i(w) J_pi dq/ddelta - [0, 0, 1] dq/ddelta``.
   The geometric residual is first divided by ``(z / 1 m)^p`` (``geometric_depth_power``; Kinect
   depth noise grows as ``z^2``), a per-pixel weight frozen during each linearisation. Each
   residual type is then divided by its own robust scale ``sigma`` (re-estimated every iteration
   for each pair); the normalised errors ``e = r / sigma`` are weighted by
   ``robust`` (IRLS): ``"student_t"`` (DVO's t-distribution with ``student_t_dof`` degrees of
   freedom, ``w = (nu + 1) / (nu + e^2)``, ``sigma`` its maximum-likelihood fixed point) or
   ``"huber"`` (``w = min(1, k / |e|)`` with ``k = huber_k`` and ``sigma = 1.4826 MAD``).
   The normal equations ``H = sum w_I / sigma_I^2 J_I^T J_I + lambda w_Z c_Z^2 / sigma_Z^2 J_Z^T J_Z``
   (``c_Z = (z / 1 m)^-p``, ``lambda = geometric_weight``) are accumulated as float32 Gram
   products over a few pixel chunks whose sums are added in float64, and solved in float64 (the
   per-pixel arithmetic is float32, both terms at once). As in DVO, a step that raises
   the mean robust cost (with the scales frozen) is undone and that pair stops at the level; a
   pair also stops when ``|delta| < tol`` (``finest_tol`` at the working resolution). Levels run
   coarse to fine. Only pixels of j with valid depth enter (compacted into a list, padded to the
   longest in a batch), and at the working resolution only one in ``finest_pixel_step`` of them
   (a quincunx for 2).
6. **Correspondences** (:func:`dense_correspondences`): at the finest level and the final pose,
   a pixel of j whose ``r_Z`` is valid and ``|r_Z| < correspondence_threshold * z`` (``z`` the
   depth of ``T_ij p_j``) pairs ``points_j = p_j`` with ``points_i = Z_i(w) ray(w)``: the point
   back-projected from the *bilinearly* interpolated depth of frame i at the landing position
   (so ``points_i`` lies on the viewing ray of ``T_ij p_j``). At most ``max_correspondences`` are
   kept, evenly spread in raster order (deterministic); each has weight ``1 / z_j^2``
   (``z_j`` the depth of ``p_j``: depth noise grows with depth). They are summarised as
   :class:`~torchslam.fastgo.PairStats`.

Convention:
    ``T_ij`` (..., 4, 4) float64 maps frame-j points into frame i: ``p_i = T_ij p_j``; i is the
    reference keyframe, j the current frame. ``PairStats`` take ``points_i`` in frame i and
    ``points_j`` in frame j, so FastGO's residual ``T_wi p_i - T_wj p_j`` vanishes at
    ``T_wj = T_wi T_ij``.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import ClassVar

import cv2
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..devices import flat_nonzero, index_select, numpy_viewable
from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, ShapeError, check_float, check_limits, check_shape, parse_choice
from ..fastgo import PairStats
from ..geometry import (
    PinholeCamera,
    backproject_depth,
    distort_normalized,
    se3_exp,
    se3_exp_numpy,
    undistorted_rays,
)
from ..optim import MAD_TO_SIGMA, solve_pair_steps

__all__ = [
    "DenseConfig",
    "DenseCorrespondences",
    "DenseFrame",
    "DenseImages",
    "DenseLevel",
    "DenseResult",
    "DenseRobust",
    "dense_correspondences",
    "dense_images",
    "prepare_dense_frame",
    "register_dense",
    "register_dense_frames",
]

logger = logging.getLogger(__name__)

# Channels of DenseLevel.reference: grey and depth, the masks, then the x gradients and the y
# gradients, so that slices give both terms' values side by side ((B, 2, N), photometric first)
# and the first _VALUE_CHANNELS are all that residuals and correspondences need (no gradients).
_GREY, _Z, _ZOK, _IOK, _GX, _ZX, _GY, _ZY = range(8)
_VALUE_CHANNELS = 4
# kornia's pyrdown (5-tap binomial blur, then the 2x2 average) as one 6-tap filter of stride 2.
_PYRDOWN_TAPS = tuple(c / 32 for c in (1, 5, 10, 10, 5, 1))
# ITU-R 601 luma weights of R, G, B (as kornia.color.rgb_to_grayscale).
_GREY_WEIGHTS = (0.299, 0.587, 0.114)
# The float32 Gram products of the normal equations are summed in float64 over this many chunks.
_GRAM_CHUNKS = 8
# ... each of at least this many residuals (coarse levels use fewer chunks).
_GRAM_CHUNK_MIN = 8192
# A bilinear sample of a {0, 1} mask counts as "all four neighbours set" above this.
_ALL_SET = 1.0 - 1e-6
# Fixed-point iterations of the t-distribution scale per Gauss-Newton iteration.
_SCALE_ITERATIONS = 5
# CPU tensors take NumPy/OpenCV fast paths where torch's fixed cost per operation dominates (the
# results agree to float round-off). Off, the CPU runs the device path (what an accelerator runs:
# the synchronisation budgets are measured on it).
HOST_FAST_PATHS = True


class DenseRobust(enum.Enum):
    """Robust weighting of the normalised residuals."""

    STUDENT_T = "student_t"
    HUBER = "huber"

    @classmethod
    def parse(cls, value: DenseRobust | str) -> DenseRobust:
        """Return the member for ``value``; a bad name lists the valid ones."""
        return parse_choice(cls, value, "robust")


@dataclass(frozen=True)
class DenseConfig:
    """Settings of the dense registration (module docstring for the method).

    Attributes:
        width, height: target working resolution, pixels. The input is reduced by the integer
            factor ``k = max(1, round(W / width))`` on both axes (remainder rows/columns on the
            right and bottom are dropped): 640x480 -> 320x240, 540x360 -> 270x180.
        levels: pyramid levels (the working resolution and ``levels - 1`` halvings).
        iterations: maximum Gauss-Newton iterations per level, coarse to fine (``levels`` values).
        geometric_weight: relative weight ``lambda`` of the geometric term. Both terms are
            divided by their own robust scale first, so it is dimensionless (1 = equal weight of
            a one-sigma photometric and a one-sigma depth error).
        geometric_depth_power: ``p`` of the depth-noise model: ``r_Z`` is divided by
            ``(z / 1 m)^p`` before its robust scale is estimated (Kinect depth noise grows as
            ``z^2``, so 2; 0 treats all depths alike), so that far points do not dominate the
            geometric term.
        robust: ``"student_t"`` (DVO) or ``"huber"``.
        student_t_dof: degrees of freedom ``nu`` of the t-distribution (DVO: 5).
        huber_k: Huber threshold in units of the scale ``sigma``.
        sigma_floor_photometric: lower bound of the photometric scale, grey levels in [0, 1]
            (keeps the weights finite on noise-free images).
        sigma_floor_geometric: lower bound of the geometric scale, metres (of the normalised
            residual, i.e. at 1 m depth).
        min_depth, max_depth: depth outside this range is invalid, metres.
        depth_merge_tolerance: a block of depths is merged (working image, pyramid) only when
            their spread is at most this fraction of the smallest; otherwise it is invalid.
        depth_edge_tolerance: a pixel whose 3x3 depth spread exceeds this fraction of its depth
            is a depth edge and gives no geometric residual.
        max_correspondences: at most this many correspondences per pair (evenly subsampled).
        correspondence_threshold: a pixel is a correspondence when ``|r_Z| < threshold * z``.
        min_correspondences: a pair with fewer correspondences is reported as failed.
        finest_pixel_step: at the working resolution the Gauss-Newton iterations use only the
            pixels of j with ``(row + column) % step == 0`` (2: a quincunx, half the pixels; 1:
            all); coarser levels and the correspondences use every pixel. 2 halves the cost of
            the finest iterations.
        tol: a pair stops at a level when its step's twist norm is below this (metres/radians).
            The IRLS steps shrink only by about half per iteration, so a tighter tolerance buys
            many iterations for sub-millimetre changes that the finer levels redo anyway; the
            default is 6e-4 (0.6 mm, 0.6 mrad). 3e-4 took about 20 % fewer iterations than 1e-4
            for the same ATE to within 0.02 cm, and 6e-4 makes registration another 1.11-1.14 x
            faster than 3e-4 with ATE within 0.005 cm (TUM fr1/xyz, 7-Scenes redkitchen, synthetic
            seeds 0-4; held out: HoloLens, seeds 100-104; ``scripts/bench_dense.py``); 1e-3 was
            1.2 x faster but 0.03 cm worse on 7-Scenes. Coarse levels only: see ``finest_tol``.
        finest_tol: ``tol`` at the working resolution (level 0). After the coarse levels have
            converged, the first step there is mostly below a millimetre, and a second iteration
            only confirms it: 1e-3 (1 mm, 1 mrad) keeps one step for nearly every pair (about 1.03
            instead of 2.3 warps at that level on TUM fr1/xyz) and iterates on only where the
            first step was large, i.e. under fast motion. Against 3e-4 registration runs about
            1.2 x faster for the same ATE (at ``tol`` 3e-4; ``scripts/bench_dense.py``; docs/results/gcslam.md,
            Results: GC-SLAM). A hard cap of one step there (``iterations[-1] = 1``) is as fast
            but loses those cases (HoloLens at every third frame 0.85 -> 1.49 cm).
    """

    width: int = 320
    height: int = 240
    levels: int = 3
    iterations: tuple[int, ...] = (20, 15, 10)
    geometric_weight: float = 2.0
    geometric_depth_power: float = 2.0
    robust: str = "student_t"
    student_t_dof: float = 5.0
    huber_k: float = 1.345
    sigma_floor_photometric: float = 1.0 / 255.0
    sigma_floor_geometric: float = 1e-3
    min_depth: float = 0.1
    max_depth: float = 10.0
    depth_merge_tolerance: float = 0.05
    depth_edge_tolerance: float = 0.1
    max_correspondences: int = 50000
    correspondence_threshold: float = 0.02
    min_correspondences: int = 1000
    tol: float = 6e-4
    finest_tol: float = 1e-3
    finest_pixel_step: int = 2

    LIMITS: ClassVar[dict[str, Limit]] = {
        "width": AT_LEAST_1, "height": AT_LEAST_1, "levels": AT_LEAST_1, "iterations": NON_NEGATIVE,
        "geometric_weight": NON_NEGATIVE, "geometric_depth_power": NON_NEGATIVE, "student_t_dof": POSITIVE,
        "huber_k": POSITIVE, "sigma_floor_photometric": POSITIVE, "sigma_floor_geometric": POSITIVE,
        "min_depth": POSITIVE, "max_depth": POSITIVE, "depth_merge_tolerance": POSITIVE, "depth_edge_tolerance": POSITIVE,
        "max_correspondences": AT_LEAST_1, "correspondence_threshold": POSITIVE, "min_correspondences": NON_NEGATIVE,
        "tol": NON_NEGATIVE, "finest_tol": NON_NEGATIVE, "finest_pixel_step": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        check_limits(self)
        its = tuple(self.iterations)
        if len(its) != self.levels:
            raise ConfigError(
                f"iterations: expected {self.levels} non-negative ints (one per level, coarse to fine), got {self.iterations!r}"
            )
        object.__setattr__(self, "iterations", its)
        DenseRobust.parse(self.robust)
        if not self.max_depth > self.min_depth:
            raise ConfigError(f"max_depth: expected a number above min_depth={self.min_depth}, got {self.max_depth!r}")


def _prep_key(cfg: DenseConfig) -> tuple:
    """The settings that shape a :class:`DenseFrame` (two frames must agree on them)."""
    return (cfg.width, cfg.height, cfg.levels, cfg.min_depth, cfg.max_depth, cfg.depth_merge_tolerance, cfg.depth_edge_tolerance)


# ---------------------------------------------------------------------------- prepared frames


@dataclass(frozen=True)
class DenseLevel:
    """One pyramid level of B prepared frames.

    Attributes:
        camera: ideal pinhole camera of the level (no distortion; size ``w x h``).
        depth_edge_tolerance: :attr:`DenseConfig.depth_edge_tolerance` (for :attr:`reference`).
        grey: (B, 1, h, w) grey in [0, 1].
        depth: (B, 1, h, w) depth, metres, 0 = invalid.
        inside: (B, 1, h, w) 0/1, the pixel's source lies inside the raw image (undistortion).
        points: (B, h*w, 3) back-projected pixels, metres, row-major (0 where invalid).
        valid: (B, h*w) bool, valid depth.
    """

    camera: PinholeCamera
    depth_edge_tolerance: float
    grey: Tensor
    depth: Tensor
    inside: Tensor
    points: Tensor
    valid: Tensor

    @functools.cached_property
    def reference(self) -> Tensor:
        """(B, 8, h, w) what the frames serve as reference frames i.

        Grey, depth, the depth-smooth mask and the inside-the-raw-image mask (eroded by one
        pixel), masks as 0/1, then the x gradients of grey (per pixel) and depth (metres per
        pixel) and their y gradients. Only a frame registered *against* needs it (a keyframe), so
        it is built on first use and kept; an indexed, expanded or concatenated frame reuses it.
        On the CPU it is stored channels-last (same values): ``grid_sample`` reads a point's
        channels side by side, about 1.5x faster.
        """
        ref = _reference(self.grey, self.depth, self.inside, self.depth_edge_tolerance)
        return ref.contiguous(memory_format=torch.channels_last) if _host(ref) else ref

    def _map(self, fn) -> DenseLevel:
        out = DenseLevel(self.camera, self.depth_edge_tolerance, *(fn(getattr(self, f.name)) for f in fields(self)[2:]))
        if "reference" in self.__dict__:
            out.__dict__["reference"] = fn(self.__dict__["reference"])
        return out


@dataclass(frozen=True)
class DenseFrame:
    """B frames prepared for dense registration: working-resolution images and their pyramid.

    A keyframe is prepared once and reused against every frame registered to it; index it,
    :meth:`expand` a single frame to a batch, or :meth:`cat` several.

    Attributes:
        levels: pyramid, finest (the working resolution) first.
        camera: the input camera the frames were prepared from.
        cfg: the settings they were prepared with.
    """

    levels: tuple[DenseLevel, ...]
    camera: PinholeCamera
    cfg: DenseConfig

    def __len__(self) -> int:
        return self.levels[0].grey.shape[0]

    def __getitem__(self, index) -> DenseFrame:
        """Select frames by int (kept as a batch of one), slice, list or index tensor."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return self._map(lambda x: x[index])

    def expand(self, batch: int) -> DenseFrame:
        """Repeat a single frame ``batch`` times without copying (views)."""
        if len(self) != 1:
            raise ShapeError(f"expand: expected a DenseFrame of 1 frame, got {len(self)}")
        return self._map(lambda x: x.expand(batch, *x.shape[1:]))

    @staticmethod
    def cat(frames: list[DenseFrame] | tuple[DenseFrame, ...]) -> DenseFrame:
        """Stack frames prepared with the same camera and settings into one batch."""
        if len(frames) == 0:
            raise ShapeError("frames: expected at least one DenseFrame, got none")
        first = frames[0]
        for m, f in enumerate(frames[1:], 1):
            _check_compatible(first, f, f"frames[{m}]")
        levels = []
        for k, lv in enumerate(first.levels):
            parts = [f.levels[k] for f in frames]
            out = DenseLevel(lv.camera, lv.depth_edge_tolerance, *(torch.cat([getattr(p, fl.name) for p in parts]) for fl in fields(lv)[2:]))
            if all("reference" in p.__dict__ for p in parts):
                out.__dict__["reference"] = torch.cat([p.reference for p in parts])
            levels.append(out)
        levels = tuple(levels)
        return DenseFrame(levels, first.camera, first.cfg)

    def images(self) -> DenseImages:
        """The working-resolution images the pyramid was built from (views, no copy)."""
        lv = self.levels[0]
        return DenseImages(lv.grey, lv.depth, lv.inside if self.camera.has_distortion else None, self.camera, self.cfg)

    def _map(self, fn) -> DenseFrame:
        return DenseFrame(tuple(lv._map(fn) for lv in self.levels), self.camera, self.cfg)


@dataclass(frozen=True)
class DenseImages:
    """B frames' working-resolution images: what their :class:`DenseFrame` is built from.

    About 8 bytes a working pixel (12 with lens distortion) against about 75 for the prepared
    pyramid with its reference channels, so a long sequence can keep every keyframe's images
    and build a pyramid only when a pair needs it (:meth:`pyramid`, the same values as
    :func:`prepare_dense_frame`).

    Attributes:
        grey: (B, 1, h, w) grey in [0, 1], undistorted.
        depth: (B, 1, h, w) depth, metres, 0 = invalid, undistorted.
        inside: (B, 1, h, w) 0/1, the pixel's source lies inside the raw image; None for a
            camera without distortion (all inside).
        camera: the input camera the images were made from.
        cfg: the settings they were made with.
    """

    grey: Tensor
    depth: Tensor
    inside: Tensor | None
    camera: PinholeCamera
    cfg: DenseConfig

    def __len__(self) -> int:
        return self.grey.shape[0]

    def pyramid(self) -> DenseFrame:
        """The prepared frames (:func:`prepare_dense_frame` of the original images)."""
        cfg, camera, grey, depth = self.cfg, self.camera, self.grey, self.depth
        inside = torch.ones_like(grey) if self.inside is None else self.inside
        k = max(1, round(camera.width / cfg.width))
        cam = replace(_level_camera(camera, 1.0 / k, grey.shape[-1], grey.shape[-2]), distortion=None)
        distorted = camera.has_distortion
        levels = [_build_level(cam, grey, depth, inside, cfg)]
        for _ in range(1, cfg.levels):
            h2, w2 = grey.shape[-2] // 2, grey.shape[-1] // 2
            grey = _pyrdown(_crop(grey, 2 * h2, 2 * w2))
            depth = _reduce_depth(_crop(depth, 2 * h2, 2 * w2), 2, cfg.depth_merge_tolerance)
            if distorted:
                # pyrdown's blur reaches 2 pixels: a coarse pixel is inside only if all it averaged was.
                inside = (_pyrdown(_crop(inside, 2 * h2, 2 * w2)) >= _ALL_SET).to(grey.dtype)
            else:
                inside = torch.ones_like(grey)
            cam = _level_camera(cam, 0.5, w2, h2)
            levels.append(_build_level(cam, grey, depth, inside, cfg))
        return DenseFrame(tuple(levels), camera, cfg)


def _check_compatible(a: DenseFrame, b: DenseFrame, name: str) -> None:
    if _prep_key(a.cfg) != _prep_key(b.cfg) or len(a.levels) != len(b.levels):
        raise ConfigError(f"{name}: prepared with different settings than the first frame ({_prep_key(b.cfg)} vs {_prep_key(a.cfg)})")
    if a.levels[0].camera != b.levels[0].camera:
        raise ShapeError(f"{name}: prepared for camera {b.levels[0].camera}, expected {a.levels[0].camera}")
    if a.levels[0].grey.dtype != b.levels[0].grey.dtype:
        raise ShapeError(f"{name}: dtype {b.levels[0].grey.dtype} differs from {a.levels[0].grey.dtype}")


def _reduce_depth(depth: Tensor, k: int, tol: float, lo: float | None = None, hi: float | None = None) -> Tensor:
    """Valid-aware k x k reduction: the mean of a block's valid depths if they agree within ``tol``.

    A depth is valid when positive, or, given ``lo`` and ``hi``, when in ``[lo, hi]`` (so NaN and
    inf are not). The k x k strided sub-images are combined elementwise: no pooling indices and
    no full-resolution masks.
    """
    h, w = depth.shape[-2] // k, depth.shape[-1] // k
    if k > 1 and depth.dtype == torch.float32 and depth.dim() == 4 and _numpy_ok(depth):
        return _reduce_depth_host(depth, k, tol, lo, hi)
    total = count = dmax = dmin = None
    for a in range(k):
        for b in range(k):
            sub = depth[..., a : h * k : k, b : w * k : k]
            v = sub > 0 if lo is None else (sub >= lo) & (sub <= hi)
            d = torch.where(v, sub, 0.0)
            dm = torch.where(v, sub, torch.inf)
            if total is None:
                total, count, dmax, dmin = d, v.to(depth.dtype), d, dm
            else:
                total, count = total + d, count + v
                dmax, dmin = torch.maximum(dmax, d), torch.minimum(dmin, dm)
    ok = (count > 0) & (dmax - dmin <= tol * dmin)
    return torch.where(ok, total / count.clamp_min(1), 0.0)


def _reduce_depth_host(depth: Tensor, k: int, tol: float, lo: float | None, hi: float | None) -> Tensor:
    """:func:`_reduce_depth` of a (B, C, H, W) float32 CPU tensor with OpenCV's single-pass
    element-wise operations: the same float32 operations in the same order, so the same bits
    (tested), at about half the time of the torch operations (640x480, k = 2). The B x C images,
    cropped to multiples of k, are stacked into one tall image, whose k x k sub-images are those
    of every image at once."""
    B, C = depth.shape[:2]
    h, w = depth.shape[-2] // k, depth.shape[-1] // k
    x = depth[..., : h * k, : w * k].numpy().reshape(B * C * h * k, w * k)
    total = count = dmax = dmin = None
    for a in range(k):
        for e in range(k):
            sub = np.ascontiguousarray(x[a::k, e::k])  # (B C h, w)
            # 255 where valid: > 0 (NaN is not), or inside [lo, hi] (NaN and inf are not).
            m = cv2.compare(sub, 0.0, cv2.CMP_GT) if lo is None else cv2.inRange(sub, lo, hi)
            d = cv2.bitwise_and(sub, sub, mask=m)  # the depth where valid, else +0
            dm = np.full_like(sub, np.inf)
            cv2.copyTo(sub, m, dm)  # the depth where valid, else inf
            if total is None:
                total, count, dmax, dmin = d, m & 1, d, dm
            else:
                total, count = cv2.add(total, d), cv2.add(count, m & 1)
                dmax, dmin = cv2.max(dmax, d), cv2.min(dmin, dm)
    ok = (count > 0) & (dmax - dmin <= np.float32(tol) * dmin)
    out = np.divide(total, np.maximum(count.astype(np.float32), np.float32(1)))
    out[~ok] = 0.0
    return torch.from_numpy(out.reshape(B, C, h, w))


def _pyrdown(x: Tensor) -> Tensor:
    """(B, C, 2h, 2w) -> (B, C, h, w): kornia's ``pyrdown`` (5x5 Gaussian with reflected borders,
    then the 2x2 average) as one separable 6-tap filter of stride 2, ``[1, 5, 10, 10, 5, 1] / 32``
    (the 5-tap binomial convolved with the 2-tap box), along each axis: twelve strided
    multiply-adds at the output's size instead of a 5x5 convolution at full size and a
    resampling (elementwise, so a frame gives the same pyramid alone or in a batch)."""
    H, W = x.shape[-2:]
    p = F.pad(x, (2, 2, 2, 2), mode="reflect")
    rows = p[..., 0:W:2] * _PYRDOWN_TAPS[0]
    for k in range(1, 6):
        rows.add_(p[..., k : k + W : 2], alpha=_PYRDOWN_TAPS[k])
    out = rows[..., 0:H:2, :] * _PYRDOWN_TAPS[0]
    for k in range(1, 6):
        out.add_(rows[..., k : k + H : 2, :], alpha=_PYRDOWN_TAPS[k])
    return out


def _crop(x: Tensor, h: int, w: int) -> Tensor:
    return x[..., :h, :w]


def _level_camera(cam: PinholeCamera, factor: float, w: int, h: int) -> PinholeCamera:
    return replace(cam.scaled(factor), width=w, height=h)


def _pool3(x: Tensor, op, fill: float) -> Tensor:
    """3x3 maximum (``op=torch.maximum``, ``fill=-inf``) or minimum of every pixel's neighbourhood,
    outside pixels ignored, as ``max_pool2d(x, 3, stride=1, padding=1)``: separable, rows then
    columns, four elementwise comparisons (the same values, several times faster on a CPU)."""
    p = F.pad(x, (1, 1, 1, 1), value=fill)
    rows = op(op(p[..., :, :-2], p[..., :, 1:-1]), p[..., :, 2:])
    return op(op(rows[..., :-2, :], rows[..., 1:-1, :]), rows[..., 2:, :])


def _min_pool3(x: Tensor) -> Tensor:
    return _pool3(x, torch.minimum, float("inf"))


def _build_level(cam: PinholeCamera, grey: Tensor, depth: Tensor, inside: Tensor, cfg: DenseConfig) -> DenseLevel:
    points, pvalid = backproject_depth(depth, cam.as_tensor(depth.dtype, depth.device))
    return DenseLevel(cam, cfg.depth_edge_tolerance, grey, depth, inside, points, pvalid)


def _reference(grey: Tensor, depth: Tensor, inside: Tensor, edge_tolerance: float) -> Tensor:
    """The (B, 8, h, w) channels of :attr:`DenseLevel.reference`."""
    g = kornia.filters.spatial_gradient(grey, mode="sobel", normalized=True)[:, 0]  # (B, 2, h, w)
    dz = kornia.filters.spatial_gradient(depth, mode="sobel", normalized=True)[:, 0]
    # Invalid depth is 0, so a positive 3x3 minimum means all nine are valid (the padding is ignored).
    zmax = _pool3(depth, torch.maximum, -float("inf"))
    zmin = _min_pool3(depth)
    smooth = (zmin > 0) & (zmax - zmin <= edge_tolerance * depth)
    inside3 = _min_pool3(inside)
    return torch.cat([grey, depth, smooth.to(grey.dtype), inside3, g[:, :1], dz[:, :1], g[:, 1:], dz[:, 1:]], dim=1)


def prepare_dense_frame(rgb: Tensor, depth: Tensor, camera: PinholeCamera, cfg: DenseConfig | None = None) -> DenseFrame:
    """Build the working-resolution grey/depth images of B frames and their pyramid.

    Args:
        rgb: (B, 3, H, W) colour in [0, 1], float32 or float64 (the prepared images keep it).
        depth: (B, 1, H, W) depth, metres; 0, non-finite or outside ``[min_depth, max_depth]``
            is invalid.
        camera: intrinsics of the input images (``width x height`` must be ``W x H``); lens
            distortion, if any, is removed by resampling (module docstring).
        cfg: settings (defaults if None).

    Returns:
        The prepared frames.

    Raises:
        ShapeError: naming the argument for bad shapes, a camera of another size, or a working
            resolution too small for the pyramid.
        DTypeError: for non-float images.
        ConfigError: for a bad ``cfg``.
    """
    cfg = _check_images(rgb, depth, camera, cfg)
    return _prepare(rgb, depth.to(rgb.dtype), camera, cfg)


def dense_images(rgb: Tensor, depth: Tensor, camera: PinholeCamera, cfg: DenseConfig | None = None) -> DenseImages:
    """The working-resolution images of B frames, without their pyramid (:class:`DenseImages`).

    ``dense_images(...).pyramid()`` equals ``prepare_dense_frame(...)``; arguments, checks and
    errors are :func:`prepare_dense_frame`'s.
    """
    cfg = _check_images(rgb, depth, camera, cfg)
    return _working_images(rgb, depth.to(rgb.dtype), camera, cfg)


def _check_images(rgb: Tensor, depth: Tensor, camera: PinholeCamera, cfg) -> DenseConfig:
    cfg = _check_cfg(cfg)
    d: dict[str, int] = {}
    check_shape(rgb, "B 3 H W", "rgb", d)
    check_shape(depth, "B 1 H W", "depth", d)
    check_float(rgb, "rgb")
    check_float(depth, "depth")
    _check_camera(camera, d["W"], d["H"], "camera")
    return cfg


def _check_cfg(cfg) -> DenseConfig:
    if cfg is None:
        return DenseConfig()
    if not isinstance(cfg, DenseConfig):
        raise ConfigError(f"cfg: expected a DenseConfig, got {type(cfg).__name__}")
    return cfg


def _check_camera(camera, W: int, H: int, name: str) -> None:
    if not isinstance(camera, PinholeCamera):
        raise ShapeError(f"{name}: expected a PinholeCamera, got {type(camera).__name__}")
    if (camera.width, camera.height) != (W, H):
        raise ShapeError(f"{name}: image size {camera.width}x{camera.height} does not match the images' {W}x{H}")


def _prepare(rgb: Tensor, depth: Tensor, camera: PinholeCamera, cfg: DenseConfig) -> DenseFrame:
    return _working_images(rgb, depth, camera, cfg).pyramid()


def _working_images(rgb: Tensor, depth: Tensor, camera: PinholeCamera, cfg: DenseConfig) -> DenseImages:
    H, W = rgb.shape[-2:]
    k = max(1, round(W / cfg.width))
    h, w = H // k, W // k
    if min(h, w) >> (cfg.levels - 1) < 8:
        raise ShapeError(
            f"rgb: {W}x{H} images give a {w}x{h} working resolution, too small for {cfg.levels} pyramid levels "
            "(the coarsest must be at least 8 pixels on each side)"
        )
    # Grey (ITU-R 601) and the k x k box average in one strided convolution.
    weight = rgb.new_tensor(_GREY_WEIGHTS).div_(k * k).view(1, 3, 1, 1).expand(1, 3, k, k).contiguous()
    grey = F.conv2d(_crop(rgb, h * k, w * k), weight, stride=k)
    if k > 1:
        depth = _reduce_depth(depth, k, cfg.depth_merge_tolerance, cfg.min_depth, cfg.max_depth)
    else:
        good = (depth >= cfg.min_depth) & (depth <= cfg.max_depth)  # False for NaN
        depth = torch.where(good, _crop(depth, h, w), 0.0)
    inside = None
    if camera.has_distortion:
        grey, depth, inside = _undistort(grey, depth, _level_camera(camera, 1.0 / k, w, h))
    return DenseImages(grey, depth, inside, camera, cfg)


def _undistort(grey: Tensor, depth: Tensor, cam: PinholeCamera) -> tuple[Tensor, Tensor, Tensor]:
    """Resample distorted working images onto the ideal pinhole grid of the same intrinsics."""
    B, _, h, w = grey.shape
    grid, inside = _undistortion_grid(cam, grey.dtype, grey.device)
    grid = grid.expand(B, h, w, 2)
    grey_u = F.grid_sample(grey, grid, mode="bilinear", padding_mode="border", align_corners=True)
    depth_u = F.grid_sample(depth, grid, mode="nearest", padding_mode="zeros", align_corners=True)
    return grey_u, depth_u * inside, inside.expand(B, 1, h, w).contiguous()


@functools.lru_cache(maxsize=8)
def _undistortion_grid(cam: PinholeCamera, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """(1, h, w, 2) sampling grid of the raw image for each ideal pixel, and (1, 1, h, w) 0/1 inside mask.

    It depends on the camera only, so it is computed once per camera (never modified by callers).
    """
    h, w = cam.height, cam.width
    rays = undistorted_rays(replace(cam, distortion=None), torch.float64, device)  # ideal rays of the output pixels
    xd = distort_normalized(rays, cam.distortion)
    u = cam.fx * xd[:, 0] + cam.cx
    v = cam.fy * xd[:, 1] + cam.cy
    grid = torch.stack([u * (2.0 / (w - 1)) - 1, v * (2.0 / (h - 1)) - 1], dim=-1).to(dtype)
    inside = ((u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)).to(dtype).reshape(1, 1, h, w)
    return grid.reshape(1, h, w, 2), inside


# ---------------------------------------------------------------------------- warp and linearisation


@dataclass(frozen=True)
class _Warp:
    """Frame-j pixels warped into frame i at one level.

    The photometric and geometric terms are kept side by side as ``(B, 2, N)`` (term 0: ``r_I``,
    term 1: ``r_Z``), so every per-pixel operation of the Gauss-Newton loop runs once for both.
    """

    q: Tensor          # (B, 3, N) T_ij p_j in frame i, channel-first
    uv: Tensor         # (B, 2, N) landing pixel (clamped into the image where it missed)
    sample: Tensor     # (B, 8, N) reference channels at uv (the first 4 without gradients)
    r: Tensor          # (B, 2, N) r_I and r_Z, metres for r_Z (0 where invalid)
    rn: Tensor         # (B, 2, N) r_I and c_Z r_Z, the residuals the robust scales see (0 where invalid)
    cn: Tensor         # (B, 2, N) 1 and the depth-noise normaliser c_Z = (z / 1 m)^-p, 0 where invalid
    m: Tensor          # (B, 2, N) bool, residual valid
    iz: Tensor         # (B, N) 1 / z (1 where the point is not in front of the camera)

    @property
    def r_I(self) -> Tensor:
        return self.r[:, 0]

    @property
    def r_Z(self) -> Tensor:
        return self.r[:, 1]

    @property
    def m_I(self) -> Tensor:
        return self.m[:, 0]

    @property
    def m_Z(self) -> Tensor:
        return self.m[:, 1]


def _warp(
    li: DenseLevel, lj: DenseLevel | _Pixels, T_ij: Tensor, min_depth: float, depth_power: float = 0.0, gradients: bool = True
) -> _Warp:
    """Warp frame j's pixels into frame i at ``T_ij``; without ``gradients`` only the first
    ``_VALUE_CHANNELS`` reference channels are sampled (no Jacobian can be built from it)."""
    if _numpy_ok(T_ij, lj.points, lj.grey, li.grey, li.depth):
        return _warp_numpy(li, lj, T_ij, min_depth, depth_power, gradients)
    dtype = li.grey.dtype
    B, _, h, w = li.grey.shape
    T = T_ij.to(dtype)
    # Channel-first (B, 3, N): every later per-pixel operation reads contiguous rows.
    q = torch.baddbmm(T[:, :3, 3:], T[:, :3, :3], lj.points.transpose(1, 2))
    x, y, z = q.unbind(1)
    front = lj.valid & (z > min_depth)
    iz = torch.where(front, z, torch.ones_like(z)).reciprocal_()
    cam = li.camera
    u = (x * iz).mul_(cam.fx).add_(cam.cx)
    v = (y * iz).mul_(cam.fy).add_(cam.cy)
    inside = front & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    # Points that miss the image are clamped onto it so every sample stays finite (they are masked).
    uv = torch.stack([u.clamp_(0, w - 1), v.clamp_(0, h - 1)], dim=1)  # (B, 2, N)
    scale = _constant((2.0 / (w - 1), 2.0 / (h - 1)), uv.dtype, uv.device)
    grid = (uv.transpose(1, 2) * scale).sub_(1.0)[:, :, None, :]  # (B, N, 1, 2)
    ref = li.reference if gradients else li.reference[:, :_VALUE_CHANNELS]
    s = F.grid_sample(ref, grid, mode="bilinear", padding_mode="border", align_corners=True)[..., 0]  # (B, 8 or 4, N)
    m_I = inside & (s[:, _IOK] >= _ALL_SET)
    m_Z = m_I & (s[:, _ZOK] >= _ALL_SET)
    m = torch.stack([m_I, m_Z], dim=1)  # (B, 2, N)
    r = s[:, _GREY : _Z + 1] - torch.stack([lj.grey.reshape(B, -1), z], dim=1)  # lj.grey: (B, 1, h, w) or (B, M)
    r = r.mul_(m)
    if depth_power == 2.0:
        c_Z = iz * iz
    elif depth_power:
        c_Z = iz.pow(depth_power)
    else:
        c_Z = torch.ones_like(iz)
    cn = torch.stack([torch.ones_like(c_Z), c_Z], dim=1).mul_(m)
    return _Warp(q, uv, s, r, r * cn, cn, m, iz)


def _warp_numpy(
    li: DenseLevel, lj: DenseLevel | _Pixels, T_ij: Tensor, min_depth: float, depth_power: float, gradients: bool
) -> _Warp:
    """:func:`_warp` on the CPU: the per-pixel arithmetic in NumPy (the same float32 operations
    in the same order), the bilinear samples by ``grid_sample`` as there; the warp's tensors
    share the arrays' memory. At the coarse levels torch's fixed cost per operation was most of
    the warp's thirty-odd operations."""
    B, _, h, w = li.grey.shape
    dt = li.grey.numpy().dtype.type
    T = T_ij.numpy().astype(dt)
    q = np.matmul(T[:, :3, :3], lj.points.numpy().transpose(0, 2, 1))
    q += T[:, :3, 3:]
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    front = lj.valid.numpy() & (z > dt(min_depth))
    iz = np.reciprocal(np.where(front, z, dt(1.0)))
    cam = li.camera
    uv = np.empty((B, 2, z.shape[-1]), dtype=dt)
    u, v = uv[:, 0], uv[:, 1]
    np.multiply(x, iz, out=u)
    u *= dt(cam.fx)
    u += dt(cam.cx)
    np.multiply(y, iz, out=v)
    v *= dt(cam.fy)
    v += dt(cam.cy)
    inside = front & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    # Points that miss the image are clamped onto it so every sample stays finite (they are masked).
    np.clip(u, 0, w - 1, out=u)
    np.clip(v, 0, h - 1, out=v)
    grid = np.empty((B, z.shape[-1], 1, 2), dtype=dt)
    np.multiply(u, dt(2.0 / (w - 1)), out=grid[:, :, 0, 0])
    np.multiply(v, dt(2.0 / (h - 1)), out=grid[:, :, 0, 1])
    grid -= dt(1.0)
    ref = li.reference if gradients else li.reference[:, :_VALUE_CHANNELS]
    s = F.grid_sample(ref, torch.from_numpy(grid), mode="bilinear", padding_mode="border", align_corners=True)[..., 0]
    sn = s.numpy()
    m = np.empty((B, 2, z.shape[-1]), dtype=bool)
    np.logical_and(inside, sn[:, _IOK] >= dt(_ALL_SET), out=m[:, 0])
    np.logical_and(m[:, 0], sn[:, _ZOK] >= dt(_ALL_SET), out=m[:, 1])
    r = sn[:, _GREY : _Z + 1] - np.stack([lj.grey.numpy().reshape(B, -1), z], axis=1)
    r *= m
    if depth_power == 2.0:
        c_Z = iz * iz
    elif depth_power:
        c_Z = iz ** dt(depth_power)
    else:
        c_Z = np.ones_like(iz)
    cn = np.stack([np.ones_like(c_Z), c_Z], axis=1)
    cn *= m
    t = torch.from_numpy
    return _Warp(t(q), t(uv), s, t(r), t(r * cn), t(cn), t(m), t(iz))


def _jacobian_rows(wp: _Warp, cam: PinholeCamera) -> Tensor:
    """(B, 7, 2, N) derivatives of ``rn`` (both terms) with respect to the left twist of ``T_ij``, then ``rn``.

    Rows 0-5 are the twist components, row 6 the residual itself, so one Gram product of the
    weighted rows gives ``J^T W J``, ``J^T W r`` and ``r^T W r``. Entries of invalid residuals are 0.
    """
    x, y, z = (c[:, None] for c in wp.q.unbind(1))  # (B, 1, N)
    s = wp.sample
    # Gradient of the residual with respect to q = T_ij p_j: (gu, gv) J_pi, minus d(z)/dq for r_Z,
    # all scaled by cn (c_Z for the geometric term, 0 where invalid).
    # With dq = rho + phi x q, dr = g . rho + (q x g) . phi, so J = [g, q x g].
    ciz = wp.cn * wp.iz[:, None]
    g0 = s[:, _GX : _ZX + 1] * ciz * cam.fx
    g1 = s[:, _GY : _ZY + 1] * ciz * cam.fy
    g2 = torch.addcmul(g0 * x, g1, y).mul_(-wp.iz[:, None])
    g2[:, 1] -= wp.cn[:, 1]
    rows = [g0, g1, g2, y * g2 - z * g1, z * g0 - x * g2, x * g1 - y * g0, wp.rn]
    return torch.stack(rows, dim=1)


def _linearize(
    li: DenseLevel, lj: DenseLevel, T_ij: Tensor, min_depth: float, depth_power: float = 0.0
) -> tuple[_Warp, Tensor, Tensor]:
    """Residuals and (B, N, 6) analytic Jacobians of ``r_I`` and ``c_Z r_Z`` at one level (module docstring, step 5)."""
    wp = _warp(li, lj, T_ij, min_depth, depth_power)
    A = _jacobian_rows(wp, li.camera)
    return wp, A[:, :6, 0].transpose(1, 2), A[:, :6, 1].transpose(1, 2)


# ---------------------------------------------------------------------------- robust weighting


@functools.lru_cache(maxsize=64)
def _constant(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """A small constant vector on ``device``, copied there once (never modified by callers).

    The Gauss-Newton loop reuses it every iteration: building it afresh from host data would
    synchronise with an accelerator each time.
    """
    return torch.tensor(values, dtype=dtype, device=device)


def _floors(cfg: DenseConfig, like: Tensor) -> Tensor:
    """(2,) lower bounds of the photometric and geometric scales."""
    return _constant((cfg.sigma_floor_photometric, cfg.sigma_floor_geometric), like.dtype, like.device)


def _scale(rn: Tensor, m: Tensor, robust: DenseRobust, cfg: DenseConfig, start: Tensor | None) -> Tensor:
    """(B, 2) robust scales of both terms' residuals ``rn`` (B, 2, N) over mask ``m``, at least their floors."""
    floor = _floors(cfg, rn)
    if robust is DenseRobust.HUBER:
        med = torch.where(m, rn.abs(), torch.full_like(rn, float("nan"))).nanmedian(dim=-1).values
        return torch.maximum(MAD_TO_SIGMA * torch.nan_to_num(med, nan=0.0), floor)
    if _numpy_ok(rn, m):
        return _scale_numpy(rn, m, cfg, floor, start)
    nu = cfg.student_t_dof
    n = m.sum(-1).clamp_min(1).to(rn.dtype)
    r2 = rn * rn  # 0 where invalid, and so are all the terms summed below
    var = r2.sum(-1) / n if start is None else start * start
    floor2 = floor * floor
    var = torch.maximum(var, floor2)
    for _ in range(_SCALE_ITERATIONS):
        # mean of r2 (nu + 1) / (nu + r2 / var) = (nu + 1) var mean(r2 / (nu var + r2)).
        t = (r2 / (r2 + (nu * var)[..., None])).sum(-1)
        var = torch.maximum(t * var * ((nu + 1) / n), floor2)
    return var.sqrt()


def _scale_numpy(rn: Tensor, m: Tensor, cfg: DenseConfig, floor: Tensor, start: Tensor | None) -> Tensor:
    """The t-distribution scales of :func:`_scale` in NumPy (CPU tensors), the same float
    arithmetic with reductions in NumPy's order: its fixed-point loop is a few passes over a few
    thousand residuals at the coarse levels, where torch's fixed cost per operation was most of
    the time (about 50 operations a call)."""
    r = rn.numpy()
    dt = r.dtype.type
    nu = dt(cfg.student_t_dof)
    n = np.maximum(m.numpy().sum(-1), 1).astype(dt)
    floor2 = floor.numpy() ** 2
    r2 = r * r  # 0 where invalid, and so are all the terms summed below
    var = r2.sum(-1) / n if start is None else start.numpy() ** 2
    var = np.maximum(var, floor2)
    buf = np.empty_like(r2)
    for _ in range(_SCALE_ITERATIONS):
        np.add(r2, (nu * var)[..., None], out=buf)
        np.divide(r2, buf, out=buf)
        var = np.maximum(buf.sum(-1) * var * ((nu + dt(1)) / n), floor2)
    return torch.from_numpy(np.sqrt(var))


def _weight(e2: Tensor, robust: DenseRobust, cfg: DenseConfig) -> Tensor:
    """IRLS weights of normalised errors given their squares ``e2``."""
    if robust is DenseRobust.HUBER:
        k = cfg.huber_k
        return (k / e2.sqrt().clamp_min_(k)).clamp_max_(1.0)
    nu = cfg.student_t_dof
    return (e2 + nu).reciprocal_().mul_(nu + 1)


def _rho(e2: Tensor, robust: DenseRobust, cfg: DenseConfig) -> Tensor:
    """Robust cost of normalised errors given their squares ``e2`` (0 at 0)."""
    if robust is DenseRobust.HUBER:
        k = cfg.huber_k
        a = e2.sqrt()
        return torch.where(a <= k, 0.5 * e2, k * (a - 0.5 * k))
    nu = cfg.student_t_dof
    return (e2 * (1.0 / nu)).log1p_().mul_(0.5 * (nu + 1))


def _term_weights(cfg: DenseConfig, like: Tensor) -> Tensor:
    """(2,) weights of the photometric and geometric mean costs: 1 and ``lambda``."""
    return _constant((1.0, cfg.geometric_weight), like.dtype, like.device)


def _scaled_sq(wp: _Warp, s: Tensor) -> Tensor:
    """(B, 2, N) squared residuals in units of their robust scales ``s`` (B, 2)."""
    if _numpy_ok(s, wp.rn):
        e = wp.rn.numpy() / s.numpy()[..., None]
        return torch.from_numpy(np.multiply(e, e, out=e))
    return (wp.rn / s[..., None]).square_()


def _cost(wp: _Warp, e2: Tensor, robust: DenseRobust, cfg: DenseConfig) -> Tensor:
    """(B,) float64 mean robust photometric cost plus ``lambda`` times the mean geometric one
    (``e2`` from :func:`_scaled_sq`)."""
    if robust is DenseRobust.STUDENT_T and _numpy_ok(e2, wp.m):
        # The same float32 arithmetic in NumPy (the CPU's per-operation cost, as _scale_numpy).
        e = e2.numpy()
        dt = e.dtype.type
        nu = cfg.student_t_dof
        rho = np.log1p(e * dt(1.0 / nu))
        mean = rho.sum(-1) * dt(0.5 * (nu + 1)) / np.maximum(wp.m.numpy().sum(-1), 1).astype(dt)
        return torch.from_numpy((mean * _term_weights(cfg, e2).numpy()).sum(-1).astype(np.float64))
    # Invalid residuals are 0 and cost 0: a plain sum over the pixels is the masked sum.
    mean = _rho(e2, robust, cfg).sum(-1) / wp.m.sum(-1).clamp_min(1)
    return (mean * _term_weights(cfg, mean)).sum(-1).double()


def _normal_equations(
    wp: _Warp, A: Tensor, e2: Tensor, s: Tensor, robust: DenseRobust, cfg: DenseConfig
) -> tuple[Tensor, Tensor]:
    """(B, 6, 6) ``H`` and (B, 6) ``g`` in float64 from the rows of :func:`_jacobian_rows` (module
    docstring, step 5); ``e2`` from :func:`_scaled_sq` with the scales ``s``."""
    B, _, _, N = A.shape
    W = _weight(e2, robust, cfg).mul_(wp.m).mul_((_term_weights(cfg, s) / (s * s))[..., None])  # (B, 2, N)
    A = A.reshape(B, 7, 2 * N)
    Aw = A * W.reshape(B, 1, 2 * N)
    # Gram products in float32 over a few chunks, summed in float64: float32 accumulation stays
    # short and the float64 conversion touches only (B, 7, 7) per chunk.
    chunks = min(_GRAM_CHUNKS, -(-2 * N // _GRAM_CHUNK_MIN))
    G = sum(torch.bmm(a, b.transpose(1, 2)).double() for a, b in zip(Aw.tensor_split(chunks, -1), A.tensor_split(chunks, -1)))
    return G[:, :6, :6], G[:, :6, 6]


def _linear_system(
    wp: _Warp, cam: PinholeCamera, e2: Tensor, s: Tensor, robust: DenseRobust, cfg: DenseConfig
) -> tuple[Tensor, Tensor]:
    """(B, 6, 6) ``H`` and (B, 6) ``g`` of a warp: :func:`_jacobian_rows` and
    :func:`_normal_equations`, on the CPU in NumPy (:func:`_linear_system_numpy`)."""
    if _numpy_ok(e2, s, wp.q, wp.sample, wp.rn, wp.cn, wp.m, wp.iz):
        return _linear_system_numpy(wp, cam, e2, s, robust, cfg)
    return _normal_equations(wp, _jacobian_rows(wp, cam), e2, s, robust, cfg)


def _linear_system_numpy(
    wp: _Warp, cam: PinholeCamera, e2: Tensor, s: Tensor, robust: DenseRobust, cfg: DenseConfig
) -> tuple[Tensor, Tensor]:
    """:func:`_jacobian_rows` and :func:`_normal_equations` in NumPy (CPU tensors): the same
    float32 rows and chunked float32 Gram products summed in float64, written into preallocated
    rows. At the coarse levels (a few thousand pixels) torch's fixed cost per operation was most
    of these forty-odd operations' time."""
    q, smp, cn, iz, rn = wp.q.numpy(), wp.sample.numpy(), wp.cn.numpy(), wp.iz.numpy()[:, None], wp.rn.numpy()
    dt = q.dtype.type
    B, _, N = q.shape
    x, y, z = q[:, 0:1], q[:, 1:2], q[:, 2:3]
    A = np.empty((B, 7, 2, N), dtype=q.dtype)
    g0, g1, g2 = A[:, 0], A[:, 1], A[:, 2]
    ciz = cn * iz
    np.multiply(smp[:, _GX : _ZX + 1], ciz, out=g0)
    g0 *= dt(cam.fx)
    np.multiply(smp[:, _GY : _ZY + 1], ciz, out=g1)
    g1 *= dt(cam.fy)
    np.multiply(g0, x, out=g2)
    g2 += g1 * y
    g2 *= -iz
    g2[:, 1] -= cn[:, 1]
    np.subtract(y * g2, z * g1, out=A[:, 3])
    np.subtract(z * g0, x * g2, out=A[:, 4])
    np.subtract(x * g1, y * g0, out=A[:, 5])
    A[:, 6] = rn
    e = e2.numpy()
    if robust is DenseRobust.HUBER:
        k = dt(cfg.huber_k)
        W = np.minimum(k / np.maximum(np.sqrt(e), k), dt(1.0))
    else:
        nu = dt(cfg.student_t_dof)
        W = np.reciprocal(e + nu)
        W *= nu + dt(1)
    W *= wp.m.numpy()
    sc = s.numpy()
    W *= (_term_weights(cfg, s).numpy() / (sc * sc))[..., None]
    A = A.reshape(B, 7, 2 * N)
    Aw = A * W.reshape(B, 1, 2 * N)
    chunks = min(_GRAM_CHUNKS, -(-2 * N // _GRAM_CHUNK_MIN))
    G = sum((a @ b.transpose(0, 2, 1)).astype(np.float64) for a, b in zip(np.array_split(Aw, chunks, -1), np.array_split(A, chunks, -1)))
    return torch.from_numpy(np.ascontiguousarray(G[:, :6, :6])), torch.from_numpy(np.ascontiguousarray(G[:, :6, 6]))


# ---------------------------------------------------------------------------- correspondences


@dataclass(frozen=True)
class DenseCorrespondences:
    """Correspondences of B pairs, padded over the finest level's pixels of frame j.

    Attributes:
        points_i: (B, N, 3) float64 points in frame i, metres (0 where not selected).
        points_j: (B, N, 3) float64 matching points in frame j, metres.
        mask: (B, N) bool, selected correspondences.
        weights: (B, N) float64 ``1 / z_j^2`` (0 where not selected), 1/m^2.
    """

    points_i: Tensor
    points_j: Tensor
    mask: Tensor
    weights: Tensor

    def stats(self) -> PairStats:
        """The FastGO statistics of the selected correspondences (B pairs)."""
        return PairStats.from_padded(self.points_i, self.points_j, mask=self.mask, weights=self.weights)


def _subsample(cand: Tensor, k: int) -> Tensor:
    """Keep at most ``k`` True entries per row, evenly spread in order (deterministic)."""
    c = cand.sum(-1, keepdim=True)
    if _host(c) and bool((c <= k).all()):  # free on the CPU: nothing to drop
        return cand
    rank = torch.cumsum(cand.to(torch.int64), dim=-1) - 1
    cs = c.clamp_min(1)
    step = (rank + 1) * k // cs > rank * k // cs
    return cand & ((c <= k) | step)


def _correspondence_mask(wp: _Warp, cfg: DenseConfig) -> Tensor:
    """(B, N) bool, the pixels kept as correspondences (module docstring, step 6)."""
    cand = wp.m_Z & (wp.r_Z.abs() < cfg.correspondence_threshold * wp.q[:, 2])
    return _subsample(cand, cfg.max_correspondences)


def _correspondences(wp: _Warp, li: DenseLevel, lj: DenseLevel | _Pixels, cfg: DenseConfig) -> DenseCorrespondences:
    keep = _correspondence_mask(wp, cfg)
    cam = li.camera
    u, v = wp.uv.double().unbind(1)
    zi = wp.sample[:, _Z].double()
    points_i = torch.stack([(u - cam.cx) / cam.fx * zi, (v - cam.cy) / cam.fy * zi, zi], dim=-1)
    points_j = lj.points.double()
    zj = points_j[..., 2]
    weights = torch.where(keep, 1.0 / torch.where(keep, zj, torch.ones_like(zj)) ** 2, torch.zeros_like(zj))
    k3 = keep[..., None]
    return DenseCorrespondences(
        torch.where(k3, points_i, torch.zeros_like(points_i)),
        torch.where(k3, points_j, torch.zeros_like(points_j)),
        keep,
        weights,
    )


def _correspondence_gram(wp: _Warp, cam: PinholeCamera, lj: DenseLevel | _Pixels, keep: Tensor) -> Tensor:
    """(B, 7, 7) float64 Gram matrices ``sum w x x^T`` of the kept correspondences' rows
    ``x = [1, p_i, p_j]``, ``w = 1 / z_j^2`` (:meth:`PairStats.from_gram`): the statistics of
    :func:`_correspondences` without its padded float64 points.

    The rows are built channel-first (the warp's layout), so the Gram product runs along
    contiguous rows; the same float64 arithmetic as :func:`_correspondences`.
    """
    u, v = wp.uv.double().unbind(1)
    zi = wp.sample[:, _Z].double()
    pj = lj.points.transpose(1, 2).double()  # (B, 3, N)
    kf = keep.to(zi.dtype)
    rows = torch.cat([kf[:, None], ((u - cam.cx) / cam.fx * zi)[:, None], ((v - cam.cy) / cam.fy * zi)[:, None], zi[:, None], pj], 1)
    rows = torch.where(keep[:, None], rows, torch.zeros_like(rows))  # (B, 7, N); 0 off the kept pixels
    zj = rows[:, 6]
    w = torch.where(keep, zj, torch.ones_like(zj)).square_().reciprocal_()
    return (rows * w[:, None]) @ rows.transpose(1, 2)


def _measured_stats(wp: _Warp, cam: PinholeCamera, px: _Pixels, keep: Tensor, count: Tensor) -> PairStats:
    return PairStats.from_gram(_correspondence_gram(wp, cam, px, keep), count)


def dense_correspondences(fi: DenseFrame, fj: DenseFrame, T_ij: Tensor, cfg: DenseConfig | None = None) -> DenseCorrespondences:
    """Select the well-aligned pixels of frame j at the working resolution as correspondences.

    Args:
        fi: B reference frames (i).
        fj: B current frames (j), prepared like ``fi``.
        T_ij: (B, 4, 4) or (4, 4) pose of frame j in frame i (``p_i = T_ij p_j``).
        cfg: settings (``fi.cfg`` if None); ``correspondence_threshold`` and
            ``max_correspondences`` apply (module docstring, step 6).

    Returns:
        The padded correspondences.
    """
    cfg, T = _check_pair(fi, fj, T_ij, cfg, "T_ij")
    wp = _warp(fi.levels[0], fj.levels[0], T, cfg.min_depth, gradients=False)
    return _correspondences(wp, fi.levels[0], fj.levels[0], cfg)


# ---------------------------------------------------------------------------- registration


@dataclass
class DenseResult:
    """Dense registration of B frame pairs.

    Attributes:
        T_ij: (B, 4, 4) float64 pose of frame j in frame i (``p_i = T_ij p_j``).
        success: (B,) bool: a finite pose and at least ``min_correspondences`` correspondences.
        num_correspondences: (B,) int64 correspondences kept.
        residual_photometric: (B,) float64 RMS of ``r_I`` over the valid pixels at the final
            pose and working resolution, grey levels in [0, 1] (inf where none is valid).
        residual_geometric: (B,) float64 RMS of ``r_Z`` likewise, metres.
        iterations: (B,) int64 Gauss-Newton steps kept (undone ones not counted), all levels.
        measure: computes :attr:`stats` (kept from the registration's last warp).
    """

    T_ij: Tensor
    success: Tensor
    num_correspondences: Tensor
    residual_photometric: Tensor
    residual_geometric: Tensor
    iterations: Tensor
    measure: Callable[[], PairStats] = field(repr=False, compare=False)

    @functools.cached_property
    def stats(self) -> PairStats:
        """FastGO statistics of the B pairs' correspondences (``points_i`` in frame i, ``points_j``
        in frame j, weights ``1 / z_j^2``), computed on first use: a tracked frame that never
        becomes a keyframe needs none (about 2 ms of a registration's 18 at 320x240 on the CPU)."""
        return self.measure()

    def __len__(self) -> int:
        return self.T_ij.shape[0]


def register_dense(
    rgb_i: Tensor,
    depth_i: Tensor,
    rgb_j: Tensor,
    depth_j: Tensor,
    camera: PinholeCamera,
    T_init: Tensor | None = None,
    cfg: DenseConfig | None = None,
) -> DenseResult:
    """Register B frame pairs densely (photometric + geometric, paper §IV-A2).

    Args:
        rgb_i: (B, 3, H, W) colour of the reference frames i in [0, 1], float32 or float64.
        depth_i: (B, 1, H, W) their depth, metres, 0 = invalid.
        rgb_j: (B, 3, H, W) colour of the current frames j.
        depth_j: (B, 1, H, W) their depth, metres.
        camera: the intrinsics of all the images (``W x H``).
        T_init: (B, 4, 4) or (4, 4) initial ``T_ij`` (identity if None).
        cfg: settings (defaults if None).

    Returns:
        Poses, success flags, residuals and the pairs' FastGO statistics.

    Raises:
        ShapeError: naming the argument for bad shapes or a camera of another size.
        DTypeError: for non-float images.
        ConfigError: for a bad ``cfg``.

    Convention:
        ``p_i = T_ij p_j`` (module docstring).
    """
    cfg = _check_cfg(cfg)
    d: dict[str, int] = {}
    for x, spec, name in (
        (rgb_i, "B 3 H W", "rgb_i"), (depth_i, "B 1 H W", "depth_i"), (rgb_j, "B 3 H W", "rgb_j"), (depth_j, "B 1 H W", "depth_j"),
    ):
        check_shape(x, spec, name, d)
        check_float(x, name)
    _check_camera(camera, d["W"], d["H"], "camera")
    if T_init is not None:
        _check_pose(T_init, d["B"], "T_init")
    fi = _prepare(rgb_i, depth_i.to(rgb_i.dtype), camera, cfg)
    fj = _prepare(rgb_j.to(rgb_i.dtype), depth_j.to(rgb_i.dtype), camera, cfg)
    return register_dense_frames(fi, fj, T_init, cfg)


def _check_pose(T: Tensor, B: int, name: str) -> Tensor:
    if isinstance(T, Tensor) and T.dim() == 2:
        check_shape(T, "4 4", name)
        T = T.expand(B, 4, 4)
    check_shape(T, "B 4 4", name, {"B": B})
    check_float(T, name)
    return T


def _check_pair(
    fi: DenseFrame, fj: DenseFrame, T_ij: Tensor | None, cfg: DenseConfig | None, pose_name: str
) -> tuple[DenseConfig, Tensor]:
    for f, name in ((fi, "fi"), (fj, "fj")):
        if not isinstance(f, DenseFrame):
            raise ShapeError(f"{name}: expected a DenseFrame, got {type(f).__name__}")
    if len(fi) != len(fj):
        raise ShapeError(f"fj: expected {len(fi)} frames like fi, got {len(fj)}")
    _check_compatible(fi, fj, "fj")
    cfg = fi.cfg if cfg is None else _check_cfg(cfg)
    if _prep_key(cfg) != _prep_key(fi.cfg):
        raise ConfigError(f"cfg: frames were prepared with {_prep_key(fi.cfg)}, cfg asks for {_prep_key(cfg)}")
    ref = fi.levels[0].grey
    if T_ij is None:
        T = torch.eye(4, dtype=torch.float64, device=ref.device).expand(len(fi), 4, 4)
    else:
        T = _check_pose(T_ij, len(fi), pose_name)
    return cfg, T.to(torch.float64).contiguous()


def register_dense_frames(
    fi: DenseFrame, fj: DenseFrame, T_init: Tensor | None = None, cfg: DenseConfig | None = None
) -> DenseResult:
    """Register B prepared pairs (a keyframe's pyramid is prepared once and reused).

    Args:
        fi: B reference frames i (e.g. ``keyframe.expand(B)``).
        fj: B current frames j, prepared with the same camera and settings.
        T_init: (B, 4, 4) or (4, 4) initial ``T_ij`` (identity if None).
        cfg: settings (``fi.cfg`` if None); its preparation settings must match the frames'.

    Returns:
        See :func:`register_dense`.
    """
    cfg, T = _check_pair(fi, fj, T_init, cfg, "T_init")
    return _register(fi, fj, T, cfg)


def _host(x: Tensor) -> bool:
    """Whether ``x`` takes the host fast paths: a plain CPU tensor (not the marked tensors of
    ``diagnostics.device_audit``'s simulated device, which stand for an accelerator's) and
    :data:`HOST_FAST_PATHS` on."""
    return HOST_FAST_PATHS and x.device.type == "cpu" and type(x) is Tensor


def _numpy_ok(*xs: Tensor) -> bool:
    """Whether the NumPy versions may stand in for torch on ``xs``: every one a host tensor
    (:func:`_host`) that needs no gradient (:func:`~torchslam.devices.numpy_viewable`)."""
    return HOST_FAST_PATHS and all(numpy_viewable(x) for x in xs)


def _gauss_newton_update(H: Tensor, g: Tensor, T: Tensor, active: Tensor, tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """Solve the B normal equations and apply the steps: ``T <- exp(delta) T`` where a pair is active and solved.

    Returns the new (B, 4, 4) poses, (B,) bool "step taken" (active and solved) and (B,) bool
    "step below ``tol``". On the CPU the 6x6 algebra runs in NumPy (:func:`_update_numpy`): the
    torch path is some fifty operations on a few numbers each, whose fixed cost per call (not
    the arithmetic) dominated a dense iteration's small work; elsewhere it stays in torch, queued
    on the device without a synchronisation.
    """
    if _host(H):
        return _update_numpy(H, g, T, active, tol)
    gn = solve_pair_steps(H, g)
    step = active & gn.solved
    T_new = torch.where(step[:, None, None], se3_exp(gn.delta) @ T, T)
    return T_new, step, torch.linalg.vector_norm(gn.delta, dim=-1) < tol


def _update_numpy(H: Tensor, g: Tensor, T: Tensor, active: Tensor, tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_gauss_newton_update` in float64 NumPy (CPU tensors). A pair whose ``H`` is not
    finite and positive definite (its least eigenvalue) takes no step, as in
    :func:`~torchslam.optim.solve_pair_steps`."""
    Hn, gn, Tn = H.numpy(), g.numpy(), T.numpy()
    if Hn.shape[0] == 1:
        T_new, step, small = _step_one(Hn[0], gn[0], Tn[0], bool(active[0]), tol)
        return T_new, torch.tensor([step]), torch.tensor([small])
    eye = np.eye(6)
    ok = np.isfinite(Hn).all((1, 2))
    Hn = np.where(ok[:, None, None], Hn, eye)
    ok &= np.linalg.eigvalsh(Hn)[:, 0] > 0
    Hn = np.where(ok[:, None, None], Hn, eye)
    delta = -np.linalg.solve(Hn, gn[..., None])[..., 0]
    solved = ok & np.isfinite(delta).all(-1)
    delta = np.where(solved[:, None], delta, 0.0)
    step = active.numpy() & solved
    E = se3_exp_numpy(delta)
    T_new = np.where(step[:, None, None], E @ Tn, Tn)
    small = np.sqrt((delta * delta).sum(-1)) < tol
    return torch.from_numpy(T_new), torch.from_numpy(step), torch.from_numpy(small)


def _step_one(H: np.ndarray, g: np.ndarray, T: np.ndarray, active: bool, tol: float) -> tuple[Tensor, bool, bool]:
    """:func:`_update_numpy` for one pair (tracking), without its batch bookkeeping: ``H`` is
    positive definite when its Cholesky factorisation exists. Returns the (1, 4, 4) pose, and
    "step taken" and "step below ``tol``" as Python bools."""
    delta = None
    if np.isfinite(H).all():
        try:
            np.linalg.cholesky(H)
            delta = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            pass
    solved = delta is not None and bool(np.isfinite(delta).all())
    if not solved:
        delta = np.zeros(6)
    step = active and solved
    T_new = se3_exp_numpy(delta[None])[0] @ T if step else T
    small = math.sqrt(float(delta @ delta)) < tol
    return torch.from_numpy(T_new[None]), step, small


@dataclass(frozen=True)
class _Pixels:
    """The pixels of B frames j that take part at one level, padded to the longest list."""

    grey: Tensor    # (B, M) grey
    points: Tensor  # (B, M, 3) back-projected, metres
    valid: Tensor   # (B, M) bool, valid depth (False on padding)


@functools.lru_cache(maxsize=16)
def _pixel_pattern(h: int, w: int, step: int, device: torch.device) -> Tensor:
    """(1, h*w) bool, ``(row + column) % step == 0`` (built once per size; never modified by callers)."""
    r = torch.arange(h, device=device)[:, None]
    c = torch.arange(w, device=device)[None, :]
    return ((r + c) % step == 0).reshape(1, -1)


def _select_pixels(lv: DenseLevel, step: int) -> _Pixels:
    """The valid-depth pixels of a level (only they give residuals), in raster order.

    With ``step > 1`` only pixels with ``(row + column) % step == 0`` are kept (a quincunx
    pattern for 2). Rows are padded to the longest list with invalid pixels.
    """
    B = lv.grey.shape[0]
    h, w = lv.grey.shape[-2:]
    keep = lv.valid
    if step > 1:
        keep = keep & _pixel_pattern(h, w, step, keep.device)
    if B == 1:
        # One frame (tracking): the kept indices directly, no padding.
        if _host(keep):  # NumPy's mask indices and row takes: several times torch's speed on the CPU
            idx = flat_nonzero(keep[0])
            take = index_select
        else:
            idx = keep[0].nonzero()[:, 0]
            take = torch.index_select
        if idx.numel() == 0:
            return _Pixels(lv.grey.reshape(1, -1)[:, :1], lv.points[:, :1], torch.zeros_like(keep[:, :1]))
        return _Pixels(take(lv.grey.reshape(-1), 0, idx)[None], take(lv.points[0], 0, idx)[None], keep.new_ones(1, idx.numel()))
    count = keep.sum(-1)
    M = max(int(count.max()), 1)
    pos = torch.where(keep, keep.cumsum(-1) - 1, M)  # slot of each kept pixel; M collects the rest
    src = torch.arange(h * w, device=keep.device).expand(B, h * w)
    idx = torch.zeros(B, M + 1, dtype=torch.int64, device=keep.device).scatter_(1, pos, src)[:, :M]
    valid = torch.arange(M, device=keep.device) < count[:, None]
    return _Pixels(lv.grey.reshape(B, -1).gather(1, idx), lv.points.gather(1, idx[..., None].expand(B, M, 3)), valid)


def _iterate_one(
    li: DenseLevel, lj: _Pixels, T: Tensor, n_iter: int, tol: float, cfg: DenseConfig, robust: DenseRobust
) -> tuple[Tensor, int]:
    """:func:`_register`'s iterations at one level for a single pair on the CPU (tracking): the
    same tensor arithmetic and decisions, with the bookkeeping (undone steps, stopping, the step
    count) in Python scalars instead of (1,)-tensors, whose fixed cost per operation was a
    measurable share of a coarse iteration. Returns the pose and the steps kept."""
    kept, T_prev, prev_cost, s = 0, T, 0.0, None
    for _ in range(n_iter):
        wp = _warp(li, lj, T, cfg.min_depth, cfg.geometric_depth_power)
        # DVO: a step that raised the cost (scales frozen) is undone and the pair stops.
        if s is not None and float(_cost(wp, _scaled_sq(wp, s), robust, cfg)) > prev_cost:
            return T_prev, kept - 1
        s = _scale(wp.rn, wp.m, robust, cfg, s)
        e2 = _scaled_sq(wp, s)
        prev_cost = float(_cost(wp, e2, robust, cfg))
        H, g = _linear_system(wp, li.camera, e2, s, robust, cfg)
        T_prev = T
        T, step, small = _step_one(H[0].numpy(), g[0].numpy(), T[0].numpy(), True, tol)
        kept += step
        if not step or small:
            break
    return T, kept


def _register_each(fi: DenseFrame, fj: DenseFrame, T: Tensor, cfg: DenseConfig) -> DenseResult:
    """:func:`_register` of B > 1 pairs on the CPU, one pair after another through the
    single-pair path (:func:`_iterate_one`), joined into one result.

    The batched path's arrays of B pairs are B times the working set of one: on the CPU the
    pairs' fresh memory, the padded pixel lists and the element-wise selections over (B, 7, N)
    rows cost more than the per-pair bookkeeping saves (5 loop pairs of fr1/xyz: about 1.3 x
    faster warm, about 3 x inside a run; docs/results/gcslam.md, "Loop pairs registered one by one"). The
    poses agree with the batched path's to rounding.
    """
    parts = [_register(fi[k], fj[k], T[k : k + 1], cfg) for k in range(len(fi))]

    def cat(name: str) -> Tensor:
        return torch.cat([getattr(p, name) for p in parts])

    return DenseResult(
        T_ij=cat("T_ij"),
        success=cat("success"),
        num_correspondences=cat("num_correspondences"),
        residual_photometric=cat("residual_photometric"),
        residual_geometric=cat("residual_geometric"),
        iterations=cat("iterations"),
        measure=lambda: PairStats.cat([p.stats for p in parts]),
    )


def _register(fi: DenseFrame, fj: DenseFrame, T: Tensor, cfg: DenseConfig) -> DenseResult:
    robust = DenseRobust.parse(cfg.robust)
    B = len(fi)
    host = _host(T)
    if host and B > 1:
        return _register_each(fi, fj, T, cfg)
    iterations = torch.zeros(B, dtype=torch.int64, device=T.device)
    # Coarse to fine: cfg.iterations[0] belongs to the coarsest level.
    for level, n_iter in zip(reversed(range(cfg.levels)), cfg.iterations):
        li, lj = fi.levels[level], fj.levels[level]
        lj = _select_pixels(lj, cfg.finest_pixel_step if level == 0 else 1)
        if host:  # one pair here (several were split above)
            T, kept = _iterate_one(li, lj, T, n_iter, cfg.tol if level else cfg.finest_tol, cfg, robust)
            iterations += kept
            continue
        active = torch.ones(B, dtype=torch.bool, device=T.device)
        T_prev, prev_cost, s = T, None, None
        for _ in range(n_iter):
            wp = _warp(li, lj, T, cfg.min_depth, cfg.geometric_depth_power)
            if prev_cost is not None:
                # DVO: a step that raised the cost (scales frozen) is undone and the pair stops.
                worse = active & (_cost(wp, _scaled_sq(wp, s), robust, cfg) > prev_cost)
                T = torch.where(worse[:, None, None], T_prev, T)
                iterations = iterations - worse.to(torch.int64)
                # No synchronisation here: when this stops the last pairs, the rest of the
                # iteration runs for nothing and changes nothing.
                active = active & ~worse
            s = _scale(wp.rn, wp.m, robust, cfg, s)
            e2 = _scaled_sq(wp, s)
            prev_cost = _cost(wp, e2, robust, cfg)
            H, g = _linear_system(wp, li.camera, e2, s, robust, cfg)
            T_prev = T
            T, step, small = _gauss_newton_update(H, g, T, active, cfg.tol if level else cfg.finest_tol)
            iterations = iterations + step.to(torch.int64)
            active = step & ~small
            if not bool(active.any()):  # the iteration's one synchronisation
                break
    # Correspondences and residuals from the valid-depth pixels only (the rest never count).
    px = _select_pixels(fj.levels[0], 1)
    wp = _warp(fi.levels[0], px, T, cfg.min_depth, gradients=False)
    keep = _correspondence_mask(wp, cfg)
    count = keep.sum(-1)
    finite = torch.isfinite(T).all(-1).all(-1)
    success = finite & (count >= cfg.min_correspondences)

    def rms(r: Tensor, m: Tensor) -> Tensor:
        n = m.sum(-1)
        val = ((r.double() ** 2 * m).sum(-1) / n.clamp_min(1)).sqrt()
        return torch.where(n > 0, val, torch.full_like(val, float("inf")))

    result = DenseResult(
        T_ij=T,
        success=success,
        num_correspondences=count,
        residual_photometric=rms(wp.r_I, wp.m_I),
        residual_geometric=rms(wp.r_Z, wp.m_Z),
        iterations=iterations,
        measure=functools.partial(_measured_stats, wp, fi.levels[0].camera, px, keep, count),
    )
    if logger.isEnabledFor(logging.DEBUG):
        logger.debug("dense registration: %d pairs, %d succeeded", B, int(success.sum()))
    return result
