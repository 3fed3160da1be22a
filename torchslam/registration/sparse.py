"""Sparse RGB-D registration of frame pairs: ORB matches, isometry filter, RANSAC, refinement.

GC-SLAM's sparse front-end (FastGO paper §IV-A1, Fig. 3):

1. ORB keypoints and descriptors (OpenCV, :func:`~torchslam.features.extract_orb`); each keypoint
   takes the depth of its nearest pixel and is lifted to a 3-D point in its camera frame.
2. Nearest-neighbour Hamming matching within ``max_distance`` bits, no ratio test: against all
   of frame i's keypoints (brute force), or, given a predicted pose, only against those that
   project near the keypoint (guided matching, :func:`guided_match`; torchslam's, for speed),
   with brute force again where the guided result is weak.
3. The isometry outlier filter (FastGO Eq. (22)): a rigid motion keeps distances, so a match is
   kept when, for at least one of ``N`` random partner matches,
   ``alpha = |1 - ||P_i^k - P_i^r|| / ||P_j^k - P_j^r|| |`` is small. Repeated for several rounds,
   each round drawing its partners among the matches the previous round kept.
4. RANSAC over rigid motions: the hypotheses of every pair are fitted (batched weighted Kabsch)
   and scored a block at a time; the best per pair wins, and a pair stops early once the
   adaptive bound on its inlier ratio says an all-inlier sample has been drawn (torchslam's).
5. Huber-weighted Gauss-Newton refinement on SE(3) over the inliers, then the inliers'
   second-order statistics (:class:`~torchslam.fastgo.PairStats`) for FastGO.

Convention:
    ``T_ij`` is the (..., 4, 4) float64 relative pose with ``p_i = T_ij p_j``: points of frame
    ``j`` (the current frame) expressed in frame ``i`` (the reference / keyframe). With
    camera-to-world poses, ``T_ij = inv(T_wi) @ T_wj``. FastGO's residual of a pair is
    ``T_wi p_i - T_wj p_j``, so the statistics hold ``points_i`` in frame i and ``points_j`` in
    frame j. Refinement updates are left-multiplicative, ``T_ij <- exp(xi) @ T_ij``, twist
    ``xi = (rho, phi)``.

Depth ``z`` of a correspondence: wherever a threshold or weight scales with depth (isometry
tolerance, inlier test, Huber scale, weight ``1 / z^2``), ``z`` is the depth of the point in frame
``i``, ``points_i[..., 2]`` (metres).

Randomness: partner and sample indices come from a counter-based hash (splitmix64) of a base seed
and the index of the match / hypothesis / slot, not from a stream of draws. A pair's random
choices therefore depend only on the base seed and on the pair's own matches, so a batch gives
the same result as one call per pair and a GPU the same as the CPU. The base seed is
``SparseConfig.seed``, or one 62-bit draw from ``generator`` when one is given.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor
from torch.nn.utils.rnn import pad_sequence

from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, DTypeError, Limit, ShapeError, check_float, check_limits, check_shape, parse_choice
from ..devices import flat_nonzero, index_select, is_host, numpy_viewable, repeat_counts
from ..fastgo import PairStats
from ..features import (
    MatchBackend,
    ORBConfig,
    extract_orb,
    hamming_distance_indexed,
    match_descriptors_batched,
)
from ..geometry import PinholeCamera, se3_exp, se3_exp_numpy, skew, umeyama_alignment, undistort_pixels
from ..optim import RobustKernel, robust_weight, solve_pair_steps

__all__ = [
    "FrameFeatures",
    "SparseConfig",
    "SparseResult",
    "frame_features",
    "guided_match",
    "isometry_filter",
    "ransac_rigid",
    "ransac_samples",
    "refine_rigid",
    "register_sparse",
    "register_sparse_batch",
]

logger = logging.getLogger(__name__)

# Elements of one (B, hypotheses, M) block of RANSAC scores: bounds memory for large batches.
_SCORE_BLOCK = 1 << 22
# RANSAC hypotheses fitted and scored together before the adaptive stopping rule is checked
# (SparseConfig.ransac_confidence): also the fewest hypotheses any pair tries.
_RANSAC_BLOCK = 50
# Bits of an ORB descriptor (the largest Hamming distance).
_BITS_MAX = 256
# Guided matching's grid: cells ``radius / _GUIDED_SPLIT`` wide, at most ``_GUIDED_CELLS`` along an
# axis (cells grow beyond that). Finer cells fit the round window better (fewer candidates).
_GUIDED_SPLIT = 4
_GUIDED_CELLS = 1024
# A guided registration whose pose moves the inliers' projections by more than this fraction of
# the window (on average) from the predicted ones is matched again around that pose: the
# prediction was off by so much that true matches near the window's edge were likely cut off.
_GUIDED_MAX_SHIFT = 0.5
# Stream identifiers of the counter-based random numbers (isometry round r uses _STREAM_ISO + r).
_STREAM_ISO = 1
_STREAM_RANSAC = 1 << 20


@dataclass(frozen=True)
class SparseConfig:
    """Settings of sparse registration.

    Defaults are those of the GC-SLAM authors' released code, which the paper does not state:
    Hamming threshold 50 without ratio test; isometry filter run 5 times with 8 random partners
    and tolerance ``0.015 z``; RANSAC with 4-point samples and 400 iterations, inlier when
    ``||R p_j + t - p_i|| / z < 0.02``, success with at least 30 inliers; 6 Huber-weighted
    Gauss-Newton refinement steps. ``huber_delta``, the depth range, ``match_backend`` and the
    guided matching keys are torchslam's choices.

    Attributes:
        max_distance: largest Hamming distance of an accepted match, bits.
        isometry_rounds: rounds of the isometry filter (0 disables it).
        isometry_partners: random partner matches per match and round (``N`` of Eq. (22)).
        isometry_tol: a match passes a round when ``alpha < isometry_tol * z`` (``z`` in metres).
            The tolerance grows with depth because depth noise does (Kinect: ``sigma_z ~ z^2``,
            so the relative error of a distance grows like ``z``).
        ransac_iterations: hypotheses per pair, at most.
        ransac_confidence: adaptive stopping (torchslam's, for speed; the released code always
            tries all ``ransac_iterations``): hypotheses are tried in blocks of 50, and a pair
            keeps the best hypothesis found once the count tried reaches
            ``log(1 - p) / log(1 - w^s)``, the number that draws an all-inlier sample with
            probability ``p`` at the best hypothesis's inlier ratio ``w`` among the filtered
            matches. 1 tries them all.
        ransac_sample: correspondences per hypothesis (at least 3).
        inlier_threshold: inlier when ``||R p_j + t - p_i|| / z`` is below this.
        min_inliers: a registration succeeds with at least this many inliers after refinement.
        refine_iterations: Gauss-Newton steps of the refinement.
        huber_delta: Huber scale on the depth-relative residual ``||R p_j + t - p_i|| / z``:
            0.01 (1 % of depth, half the inlier threshold) keeps the quadratic zone above the
            Kinect's noise at 1-4 m while halving the pull of residuals near the threshold.
        min_depth: keypoints with depth below this (metres) get no 3-D point.
        max_depth: keypoints with depth above this (metres) get no 3-D point.
        seed: base seed of the random choices when no generator is given.
        match_backend: ``auto`` matches each pair on the CPU with one int8 GEMM or with
            OpenCV, whichever a timing at the process's first match found faster
            (:func:`torchslam.features.matching.cpu_auto_backend`; both faster there than the
            batched torch kernel for the few pairs of one step), and all pairs at once in torch
            elsewhere; ``int8``, ``opencv`` or ``torch`` force one. All give the same matches.
        guided_radius: window of guided matching, pixels (0 disables it). When a predicted pose
            is given (:func:`register_sparse_batch`'s ``T_pred``), each frame-j keypoint is
            compared only with the frame-i keypoints whose 3-D points, moved by the prediction,
            project within this distance of it (:func:`guided_match`), instead of with all of
            them. torchslam's choice (not in the paper or the released code): 20 pixels covers
            the constant-velocity prediction's error on 98 % of the frames of TUM fr1/xyz (90th
            percentile over a frame's points: median 3.7 px, 98th percentile 14.8 px) and all
            of 7-Scenes redkitchen's (at most 10 px).
        guided_min_inliers: a guided registration with fewer inliers than this (torchslam's
            choice) or a failed one is redone with brute-force matching, so a bad prediction
            (fast motion, a lost frame) costs time, not accuracy; the brute-force result is
            kept where the guided one failed or kept fewer inliers. One whose pose moves the
            inliers' projections by more than half the window on average from the predicted
            ones is first matched again, guided by that pose.
        guided_min_fraction: a guided registration whose inliers number fewer than this fraction
            of the keypoints with depth (the fewer of the two frames') is redone with brute-force
            matching too (torchslam's choice, 0 disables it). A prediction far off (no motion
            prior, a sudden turn) can lock the window onto a wrong but self-consistent set of
            matches that passes ``guided_min_inliers``: on a 5 Hz synthetic walk started from
            the last pose, 72-74 inliers of ~1,900 keypoints (4 %) put a frame 45 cm off, where
            brute force kept 820. Right guided registrations keep 15-80 % (TUM fr1/xyz at least
            15 %, 7-Scenes redkitchen 29 %); below 20 % costs a brute-force match on 2 % of
            fr1/xyz's registrations and none of 7-Scenes'.
    """

    max_distance: int = 50
    isometry_rounds: int = 5
    isometry_partners: int = 8
    isometry_tol: float = 0.015
    ransac_iterations: int = 400
    ransac_sample: int = 4
    ransac_confidence: float = 0.999
    inlier_threshold: float = 0.02
    min_inliers: int = 30
    refine_iterations: int = 6
    huber_delta: float = 0.01
    min_depth: float = 0.1
    max_depth: float = 10.0
    seed: int = 0
    match_backend: MatchBackend | str = MatchBackend.AUTO
    guided_radius: float = 20.0
    guided_min_inliers: int = 50
    guided_min_fraction: float = 0.2

    LIMITS: ClassVar[dict[str, Limit]] = {
        "max_distance": Limit(ge=0, le=256), "isometry_rounds": NON_NEGATIVE, "isometry_partners": AT_LEAST_1,
        "isometry_tol": POSITIVE, "ransac_iterations": AT_LEAST_1, "ransac_sample": Limit(ge=3),
        "ransac_confidence": Limit(gt=0, le=1),
        "inlier_threshold": POSITIVE, "min_inliers": NON_NEGATIVE, "refine_iterations": NON_NEGATIVE,
        "huber_delta": POSITIVE, "min_depth": POSITIVE, "max_depth": POSITIVE, "seed": Limit(),
        "guided_radius": NON_NEGATIVE, "guided_min_inliers": NON_NEGATIVE, "guided_min_fraction": Limit(ge=0, le=1),
    }

    def __post_init__(self) -> None:
        check_limits(self)
        if not self.max_depth > self.min_depth:
            raise ConfigError(f"SparseConfig.max_depth: expected > min_depth={self.min_depth}, got {self.max_depth}")
        object.__setattr__(self, "match_backend", parse_choice(MatchBackend, self.match_backend, "SparseConfig.match_backend"))


@dataclass(frozen=True)
class FrameFeatures:
    """ORB features of one RGB-D frame with the 3-D point of each keypoint.

    Attributes:
        keypoints: (K, 2) float32 pixel coordinates ``(u, v)``, pixel centres at integers.
        descriptors: (K, 32) uint8 ORB descriptors.
        points: (K, 3) float64 points in the camera frame, metres; rows without valid depth are 0.
        valid: (K,) bool, True where the keypoint has depth in ``[min_depth, max_depth]``.
    """

    keypoints: Tensor
    descriptors: Tensor
    points: Tensor
    valid: Tensor

    def __post_init__(self) -> None:
        d: dict[str, int] = {}
        check_shape(self.keypoints, "K 2", "keypoints", d)
        check_shape(self.descriptors, "K 32", "descriptors", d)
        check_shape(self.points, "K 3", "points", d)
        check_shape(self.valid, "K", "valid", d)
        check_float(self.keypoints, "keypoints")
        check_float(self.points, "points")
        if self.descriptors.dtype != torch.uint8:
            raise DTypeError(f"descriptors: expected uint8, got {self.descriptors.dtype}")
        if self.valid.dtype != torch.bool:
            raise DTypeError(f"valid: expected bool, got {self.valid.dtype}")

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def to(self, device: torch.device | str) -> FrameFeatures:
        """Return the same features on ``device``."""
        return FrameFeatures(
            self.keypoints.to(device), self.descriptors.to(device), self.points.to(device), self.valid.to(device)
        )


@dataclass
class SparseResult:
    """Registration of B frame pairs (see the module's convention).

    Matches are padded to a common length M; row ``m < num_matches[b]`` of pair b is a real
    match, ordered by keypoint index in frame j. Padded rows are zero and never inliers.

    Attributes:
        T_ij: (B, 4, 4) float64 relative poses, ``p_i = T_ij p_j``; a failed pair keeps the
            best estimate found, or the identity when there was none.
        success: (B,) bool, True with at least ``min_inliers`` inliers after refinement.
        num_matches: (B,) int64 matches with valid depth on both sides.
        num_filtered: (B,) int64 matches kept by the isometry filter.
        num_inliers: (B,) int64 inliers at ``T_ij``.
        points_i: (B, M, 3) float64 matched points in frame i, metres.
        points_j: (B, M, 3) float64 matched points in frame j, metres.
        inliers: (B, M) bool inlier mask at ``T_ij``.
        weights: (B, M) float64 ``1 / z_i^2`` on inliers (``z_i`` = depth of the point in frame
            i, metres), 0 elsewhere.
        rmse: (B,) root-mean-square of ``||R p_j + t - p_i||`` over the inliers, metres (0 for a
            pair without inliers).
        stats: FastGO statistics of the B pairs from the weighted inliers.
        pixels_j: (B, M, 2) float32 keypoint pixels in frame j of each match.
        guided: (B,) bool, True where the matches are guided ones (:func:`guided_match`),
            False where they come from brute-force matching.
    """

    T_ij: Tensor
    success: Tensor
    num_matches: Tensor
    num_filtered: Tensor
    num_inliers: Tensor
    points_i: Tensor
    points_j: Tensor
    inliers: Tensor
    weights: Tensor
    rmse: Tensor
    stats: PairStats
    pixels_j: Tensor
    guided: Tensor | None = None

    def __len__(self) -> int:
        return int(self.T_ij.shape[0])


# ---------------------------------------------------------------------------- features


def _interpolate_rays(grid: Tensor, uv: Tensor) -> Tensor:
    """Bilinear interpolation of an (H, W, 2) ray grid at (K, 2) pixel positions (clamped inside)."""
    H, W = grid.shape[:2]
    u = uv[:, 0].clamp(0, W - 1)
    v = uv[:, 1].clamp(0, H - 1)
    u0 = u.floor().long().clamp(max=W - 2) if W > 1 else u.floor().long()
    v0 = v.floor().long().clamp(max=H - 2) if H > 1 else v.floor().long()
    a = (u - u0)[:, None]
    b = (v - v0)[:, None]
    u1 = (u0 + 1).clamp(max=W - 1)
    v1 = (v0 + 1).clamp(max=H - 1)
    top = grid[v0, u0] * (1 - a) + grid[v0, u1] * a
    bottom = grid[v1, u0] * (1 - a) + grid[v1, u1] * a
    return top * (1 - b) + bottom * b


def frame_features(
    rgb: Tensor,
    depth: Tensor,
    camera: PinholeCamera,
    orb: ORBConfig | None = None,
    cfg: SparseConfig | None = None,
    rays: Tensor | None = None,
) -> FrameFeatures:
    """Extract ORB features of one RGB-D frame and lift each keypoint to 3-D.

    Each keypoint takes the depth of its nearest pixel (depth is registered to colour); depth
    outside ``[cfg.min_depth, cfg.max_depth]`` (0 included) marks it invalid. The point lies on
    the viewing ray through the keypoint's sub-pixel position, with lens distortion removed when
    ``camera`` has any: ``(x z, y z, z)``.

    Args:
        rgb: (3, H, W) float32/float64 colour in [0, 1].
        depth: (1, H, W) float32/float64 depth, metres, 0 = invalid.
        camera: intrinsics of the (H, W) image, with optional distortion.
        orb: detector settings (default ``ORBConfig()``: 2000 features, 8 levels, scale 1.2).
        cfg: registration settings (depth range).
        rays: optional (H*W, 2) undistorted normalised rays of every pixel
            (:func:`~torchslam.geometry.undistorted_rays` of ``camera``, computed once per
            camera); the keypoints' rays are then interpolated bilinearly from it instead of
            inverting the distortion per keypoint (same rays to ~1e-7, and cheaper).

    Returns:
        The frame's features (K may be 0 for an image without corners).

    Raises:
        ShapeError: ``rgb``/``depth`` shapes disagree, or ``camera`` is not a PinholeCamera of
            the image size.
        DTypeError: a non-float image.
    """
    dims: dict[str, int] = {}
    check_shape(rgb, "3 H W", "rgb", dims)
    check_shape(depth, "1 H W", "depth", dims)
    check_float(rgb, "rgb")
    check_float(depth, "depth")
    if not isinstance(camera, PinholeCamera):
        raise ShapeError(f"camera: expected a PinholeCamera, got {type(camera).__name__}")
    if (camera.height, camera.width) != (dims["H"], dims["W"]):
        raise ShapeError(f"camera: expected an image size of {dims['W']}x{dims['H']} like rgb, got {camera.width}x{camera.height}")
    cfg = SparseConfig() if cfg is None else cfg
    feats = extract_orb(rgb, orb)
    kp = feats.keypoints
    H, W = dims["H"], dims["W"]
    col = (kp[:, 0] + 0.5).floor().long().clamp_(0, W - 1)  # nearest pixel, halves round up
    row = (kp[:, 1] + 0.5).floor().long().clamp_(0, H - 1)
    z = depth[0, row, col].to(torch.float64)
    valid = torch.isfinite(z) & (z >= cfg.min_depth) & (z <= cfg.max_depth)
    uv = kp.to(torch.float64)
    if rays is not None:
        check_shape(rays, f"{H * W} 2", "rays")
        xy = _interpolate_rays(rays.to(torch.float64).view(H, W, 2), uv)
    elif camera.has_distortion:
        xy = undistort_pixels(uv, camera, newton_steps=3)
    else:
        xy = torch.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], -1)
    z = torch.where(valid, z, torch.zeros_like(z))
    points = torch.cat([xy * z[:, None], z[:, None]], -1)
    return FrameFeatures(kp, feats.descriptors, points, valid)


# ---------------------------------------------------------------------------- randomness


def _s64(x: int) -> int:
    x &= (1 << 64) - 1
    return x - (1 << 64) if x >= 1 << 63 else x


_GOLDEN = _s64(0x9E3779B97F4A7C15)
_MIX1 = _s64(0xBF58476D1CE4E5B9)
_MIX2 = _s64(0x94D049BB133111EB)


def _shr(x: Tensor, k: int) -> Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic)."""
    return (x >> k) & ((1 << (64 - k)) - 1)


def _mix(x: Tensor) -> Tensor:
    """splitmix64: one step of the state and its finaliser, on int64 with wrapping arithmetic."""
    z = x + _GOLDEN
    z = (z ^ _shr(z, 30)) * _MIX1
    z = (z ^ _shr(z, 27)) * _MIX2
    return z ^ _shr(z, 31)


def _uniform(seed: int, stream: int | Tensor, *index: Tensor) -> Tensor:
    """Counter-based uniforms in [0, 1): a hash of (seed, stream, broadcast int64 indices).

    ``stream`` may be an int64 tensor that broadcasts with the indices (several streams at once).

    Returns:
        float64 tensor of the indices' broadcast shape; 53 random bits each.
    """
    dev = index[0].device
    if is_host(index[0]) and (not isinstance(stream, Tensor) or is_host(stream)):
        return torch.from_numpy(_uniform_numpy(seed, stream, index))
    h = _mix(torch.tensor(_s64(seed), dtype=torch.int64, device=dev))
    h = _mix(h + stream)
    for idx in index:
        h = _mix(h + idx)
    return _shr(h, 11).to(torch.float64) * 2.0**-53


_GOLDEN_U, _MIX1_U, _MIX2_U = (np.uint64(c) for c in (0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB))


def _mix_numpy(z: np.ndarray) -> np.ndarray:
    """:func:`_mix` on uint64 (NumPy's shifts of unsigned words are logical, its arithmetic wraps)."""
    z = z + _GOLDEN_U
    z ^= z >> np.uint64(30)
    z *= _MIX1_U
    z ^= z >> np.uint64(27)
    z *= _MIX2_U
    z ^= z >> np.uint64(31)
    return z


def _uniform_numpy(seed: int, stream, index) -> np.ndarray:
    """:func:`_uniform` on host tensors in NumPy, the same bits: the hash's dozen operations per
    step cost torch's fixed overhead each, several times NumPy's on these small arrays."""

    def words(x) -> np.ndarray:
        return x.numpy().astype(np.uint64) if isinstance(x, Tensor) else np.array(x % (1 << 64), dtype=np.uint64)

    with np.errstate(over="ignore"):
        h = _mix_numpy(np.array([seed % (1 << 64)], dtype=np.uint64))
        h = _mix_numpy(h + words(stream))
        for idx in index:
            h = _mix_numpy(h + words(idx))
        h = h.reshape(np.broadcast_shapes(*(tuple(i.shape) for i in index), tuple(getattr(stream, "shape", ()))))
        return (h >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _base_seed(cfg: SparseConfig, generator: torch.Generator | None) -> int:
    if generator is None:
        return int(cfg.seed)
    if not isinstance(generator, torch.Generator):
        raise ConfigError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
    return int(torch.randint(0, 1 << 62, (1,), generator=generator, device=generator.device))


# ---------------------------------------------------------------------------- isometry filter


def _check_corr(p_i: Tensor, p_j: Tensor, valid: Tensor, dims: dict) -> None:
    check_shape(p_i, "B M 3", "p_i", dims)
    check_shape(p_j, "B M 3", "p_j", dims)
    check_shape(valid, "B M", "valid", dims)
    check_float(p_i, "p_i")
    check_float(p_j, "p_j")
    if valid.dtype != torch.bool:
        raise DTypeError(f"valid: expected a bool mask, got {valid.dtype}")


def _isometry_filter(p_i: Tensor, p_j: Tensor, valid: Tensor, cfg: SparseConfig, seed: int) -> Tensor:
    B, M = valid.shape
    if M == 0 or cfg.isometry_rounds == 0:
        return valid.clone()
    if p_i.dtype == p_j.dtype and all(numpy_viewable(x) for x in (p_i, p_j, valid)):
        return torch.from_numpy(_isometry_filter_numpy(p_i.numpy(), p_j.numpy(), valid.numpy(), cfg, seed))
    dev = p_i.device
    R, N = cfg.isometry_rounds, cfg.isometry_partners
    m_idx = torch.arange(M, device=dev)[:, None]  # (M, 1)
    t_idx = torch.arange(N, device=dev)[None, :]  # (1, N)
    # Every round's uniforms at once: stream _STREAM_ISO + r for round r, keyed by match index.
    u_all = _uniform(seed, _STREAM_ISO + torch.arange(R, device=dev)[:, None, None], m_idx, t_idx)  # (R, M, N)
    tol = cfg.isometry_tol * p_i[..., 2]  # (B, M)
    # alpha = |1 - d_i / d_j| < tol  <=>  (1 - tol)^2 d_j^2 < d_i^2 < (1 + tol)^2 d_j^2 (lower bound
    # only where tol < 1), so squared distances suffice; d_j = 0 never passes.
    lo2 = torch.where(tol < 1, (1 - tol) ** 2, torch.full_like(tol, -1.0))[..., None]  # (B, M, 1)
    hi2 = ((1 + tol) ** 2)[..., None]
    # Both frames' coordinates as six planes over the B * M matches, so a round's partners are
    # one gather and its squared distances sums of contiguous planes.
    planes = torch.cat([p_i, p_j], -1).permute(2, 0, 1).reshape(6, B * M)
    row0 = (torch.arange(B, device=dev) * M)[:, None]  # (B, 1) first row of each pair
    kept = valid.clone()
    for r in range(R):
        count = kept.sum(-1)  # (B,)
        rank = kept.cumsum(-1) - 1  # (B, M) rank of each kept match among the kept
        order = torch.argsort((~kept).to(torch.int8), dim=-1, stable=True)  # kept positions first
        # Uniform over the other kept matches: draw among count - 1 ranks and skip one's own.
        draw = (u_all[r][None] * (count - 1).clamp_min(0)[:, None, None]).floor().to(torch.int64)
        draw = draw + (draw >= rank[..., None]).to(torch.int64)
        partner = (order + row0).reshape(-1).index_select(0, (draw.clamp(0, M - 1) + row0[..., None]).reshape(-1))
        d = planes.view(6, B, M, 1) - index_select(planes, 1, partner).view(6, B, M, N)
        d = d * d
        di2 = d[0] + d[1] + d[2]  # (B, M, N)
        dj2 = d[3] + d[4] + d[5]
        passed = (di2 < hi2 * dj2) & (di2 > lo2 * dj2) & (dj2 > 0)  # Eq. (22) for one partner
        kept = kept & (count >= 2)[:, None] & passed.any(-1)
    return kept


def _isometry_filter_numpy(p_i: np.ndarray, p_j: np.ndarray, valid: np.ndarray, cfg: SparseConfig, seed: int) -> np.ndarray:
    """:func:`_isometry_filter` on host arrays, the same partners and arithmetic (so the same
    result), computed for the kept matches only: a kept match's partners are always kept ones,
    and the torch path's values for the others are masked out. All pairs at once: the kept
    matches of every pair in one flat list, each pair's a contiguous run of it. A match needs
    one partner to pass, so each round tests every match's first partner, and the other
    partners only of the matches that one failed (most inliers pass with the first)."""
    B, M = valid.shape
    R, N = cfg.isometry_rounds, cfg.isometry_partners
    u_all = _uniform_numpy(seed, _STREAM_ISO + torch.arange(R)[:, None, None], (torch.arange(M)[:, None], torch.arange(N)[None, :]))
    planes = np.concatenate([p_i, p_j], -1).reshape(B * M, 6).T.copy()  # (6, B * M) contiguous rows
    tol = cfg.isometry_tol * planes[2]
    lo2 = np.where(tol < 1, (1 - tol) ** 2, -1.0)
    hi2 = (1 + tol) ** 2

    def passes(rows: np.ndarray, partners: np.ndarray) -> np.ndarray:
        """Eq. (22) for matches ``rows`` (K,) against their ``partners`` (K, P): (K, P) bool."""
        d = np.take(planes, rows, axis=1)[:, :, None] - np.take(planes, partners, axis=1)  # (6, K, P)
        d *= d
        di2 = d[0] + d[1] + d[2]
        dj2 = d[3] + d[4] + d[5]
        return (di2 < hi2[rows, None] * dj2) & (di2 > lo2[rows, None] * dj2) & (dj2 > 0)

    kept = valid.reshape(-1).copy()
    for r in range(R):
        at = np.flatnonzero(kept)  # flat positions of the kept matches, pair by pair
        if not len(at):
            break
        pair = at // M
        count = np.bincount(pair, minlength=B)
        first = (np.cumsum(count) - count)[pair]  # where each kept match's pair starts in ``at``
        n = count[pair]
        rank = np.arange(len(at)) - first
        run = (u_all[r], at, first, n, rank, M)
        passed = passes(at, _iso_partners(run, np.arange(len(at)), slice(0, 1)))[:, 0]
        if N > 1:
            again = np.flatnonzero(~passed)
            if len(again):
                passed[again] = passes(at[again], _iso_partners(run, again, slice(1, N))).any(-1)
        kept[at] = passed & (n >= 2)
    return kept.reshape(B, M)


def _iso_partners(run: tuple, k: np.ndarray, cols: slice) -> np.ndarray:
    """Partner slots ``cols`` of the kept matches ``k`` (indices into the round's ``at``), as flat
    match positions: uniform over the other kept matches of the pair (count - 1 ranks, one's own
    skipped), as :func:`_isometry_filter` draws them. ``run``: the round's uniforms (M, N), kept
    positions, each one's pair start in them, pair count and rank, and M."""
    u, at, first, n, rank, M = run
    m1 = n[k] - 1
    draw = np.floor(u[at[k] % M, cols] * np.maximum(m1, 0)[:, None]).astype(np.int64)
    draw += draw >= rank[k, None]
    return at[first[k, None] + np.minimum(draw, m1[:, None])]  # clamped only where n < 2


def isometry_filter(
    p_i: Tensor,
    p_j: Tensor,
    valid: Tensor,
    cfg: SparseConfig | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Remove matches that break the isometry of rigid motions (FastGO Eq. (22)), batched.

    In each of ``cfg.isometry_rounds`` rounds, every kept match ``k`` draws
    ``cfg.isometry_partners`` partners ``r`` uniformly among the *other* matches still kept (so
    later rounds draw from a cleaner set) and computes
    ``alpha_k = min_r |1 - ||p_i^k - p_i^r|| / ||p_j^k - p_j^r|| |``. It stays kept when
    ``alpha_k < isometry_tol * z_k``. A true match needs one inlier partner to pass; an outlier
    passes only by chance, and must do so in every round. Partners at zero distance in frame j
    do not vote.

    Args:
        p_i: (B, M, 3) matched points in frame i, metres.
        p_j: (B, M, 3) matched points in frame j, metres.
        valid: (B, M) bool, real matches (padding False).
        cfg: filter settings.
        generator: source of the base seed (``cfg.seed`` when None); see the module docstring.

    Returns:
        (B, M) bool, matches kept (a subset of ``valid``).
    """
    dims: dict[str, int] = {}
    _check_corr(p_i, p_j, valid, dims)
    cfg = SparseConfig() if cfg is None else cfg
    return _isometry_filter(p_i, p_j.to(p_i.dtype), valid, cfg, _base_seed(cfg, generator))


# ---------------------------------------------------------------------------- RANSAC


def _ransac_samples(valid: Tensor, cfg: SparseConfig, seed: int) -> tuple[Tensor, Tensor]:
    B, M = valid.shape
    dev = valid.device
    H, s = cfg.ransac_iterations, cfg.ransac_sample
    count = valid.sum(-1)  # (B,)
    order = torch.argsort((~valid).to(torch.int8), dim=-1, stable=True)
    h_idx = torch.arange(H, device=dev)[:, None]
    t_idx = torch.arange(s, device=dev)[None, :]
    u = _uniform(seed, _STREAM_RANSAC, h_idx, t_idx)  # (H, s), keyed by hypothesis and slot
    chosen = torch.zeros(B, H, 0, dtype=torch.int64, device=dev)  # ascending ranks drawn so far
    draws = []
    for t in range(s):
        # Draw among the count - t ranks not yet taken, then step over the taken ones in
        # ascending order: a uniform sample without replacement.
        r = (u[None, :, t] * (count - t).clamp_min(0)[:, None]).floor().to(torch.int64)  # (B, H)
        for k in range(t):
            r = r + (r >= chosen[..., k]).to(torch.int64)
        draws.append(r)
        chosen = torch.sort(torch.cat([chosen, r[..., None]], -1), dim=-1).values
    ranks = torch.stack(draws, -1).clamp(0, max(M - 1, 0))  # (B, H, s)
    if M == 0:
        return ranks, count >= s
    idx = order.gather(1, ranks.reshape(B, -1)).reshape(B, H, s)
    return idx, count >= s


def ransac_samples(
    valid: Tensor, cfg: SparseConfig | None = None, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Draw the RANSAC minimal samples of B pairs, the ones :func:`ransac_rigid` fits.

    Each hypothesis draws ``cfg.ransac_sample`` distinct matches uniformly among the ``valid``
    ones of its pair.

    Args:
        valid: (B, M) bool candidate matches.
        cfg: RANSAC settings.
        generator: source of the base seed (``cfg.seed`` when None).

    Returns:
        idx: (B, H, s) int64 match indices of every hypothesis (meaningless where not ``ok``).
        ok: (B,) bool, True where the pair has at least ``s`` candidates.
    """
    check_shape(valid, "B M", "valid")
    if valid.dtype != torch.bool:
        raise DTypeError(f"valid: expected a bool mask, got {valid.dtype}")
    cfg = SparseConfig() if cfg is None else cfg
    return _ransac_samples(valid, cfg, _base_seed(cfg, generator))


def _eye4(ref: Tensor, B: int) -> Tensor:
    return torch.eye(4, dtype=ref.dtype, device=ref.device).expand(B, 4, 4).clone()


def _inliers_at(p_i: Tensor, p_j: Tensor, mask: Tensor, T: Tensor, thr: float) -> tuple[Tensor, Tensor]:
    """Inlier mask (B, M) and residual vectors (B, M, 3) ``R p_j + t - p_i`` at ``T`` (B, 4, 4)."""
    r = p_j @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3] - p_i
    sq = (r * r).sum(-1)
    z = p_i[..., 2]
    return mask & (sq < (thr * z) ** 2), r


def _ransac_needed(best: Tensor, candidates: Tensor, sample: int, confidence: float) -> Tensor:
    """(B,) hypotheses that find an all-inlier sample with probability ``confidence``.

    The standard adaptive RANSAC bound ``log(1 - p) / log(1 - w^s)`` (Hartley and Zisserman,
    Multiple View Geometry, Alg. 4.5) with the inlier ratio ``w`` of the best hypothesis so far:
    0 where every candidate is an inlier, infinite where none is or where ``confidence`` is 1.
    """
    if confidence >= 1.0:
        return torch.full(best.shape, float("inf"), dtype=torch.float64, device=best.device)
    w = best.clamp_min(0).to(torch.float64) / candidates.clamp_min(1).to(torch.float64)
    return math.log1p(-confidence) / torch.log1p(-(w**sample).clamp_max(1.0))


def _ransac_from_samples(p_i: Tensor, p_j: Tensor, valid: Tensor, idx: Tensor, ok: Tensor, cfg: SparseConfig):
    B, M = valid.shape
    H, s = idx.shape[1], idx.shape[2]
    if M == 0:
        return _eye4(p_i, B), valid.clone()
    dev = p_i.device
    # Score against the candidates only: move them to the front and drop the columns no pair uses.
    cand = torch.argsort((~valid).to(torch.int8), dim=-1, stable=True)[:, : int(valid.sum(-1).max())]
    q_i = p_i.gather(1, cand[..., None].expand(-1, -1, 3))
    q_j = p_j.gather(1, cand[..., None].expand(-1, -1, 3))
    q_valid = valid.gather(1, cand)
    Mc = cand.shape[1]
    # ||R p_j + t - p_i||^2 expanded into one batched product of per-hypothesis and per-match
    # features (16 each), so the (B, H, M, 3) residual vectors are never formed:
    # |p_j|^2 + |p_i|^2 + |t|^2 - 2 <R, p_i p_j^T> - 2 t.p_i + 2 (R^T t).p_j.
    f_m = torch.cat(
        [-2 * (q_i[..., :, None] * q_j[..., None, :]).reshape(B, Mc, 9), -2 * q_i, 2 * q_j, torch.ones_like(q_i[..., :1])],
        -1,
    ).transpose(1, 2)  # (B, 16, Mc)
    base = (q_i * q_i).sum(-1) + (q_j * q_j).sum(-1)  # (B, Mc)
    limit = (cfg.inlier_threshold * q_i[..., 2]) ** 2 - base  # inlier when f_h . f_m < limit
    limit = torch.where(q_valid, limit, torch.full_like(limit, -float("inf")))
    num_candidates = q_valid.sum(-1)  # (B,)
    rows = torch.arange(B, device=dev)
    best_count = torch.full((B,), -1, dtype=torch.int64, device=dev)
    T = _eye4(p_i, B)
    done = ~ok  # a pair without a minimal sample has nothing to try (and must not hold the others up)
    # Hypotheses are fitted and scored a block at a time. A pair stops taking new bests once the
    # hypotheses so far reach the adaptive bound of its best inlier ratio (cfg.ransac_confidence),
    # the same rule on every device; on the host the loop also ends once every pair has stopped.
    block = min(H, _RANSAC_BLOCK) if cfg.ransac_confidence < 1.0 else H
    step = max(1, _SCORE_BLOCK // max(1, B * Mc))
    host = is_host(p_i)
    for h0 in range(0, H, block):
        h1 = min(H, h0 + block)
        g = idx[:, h0:h1].reshape(B, (h1 - h0) * s, 1).expand(-1, -1, 3)
        src = p_j.gather(1, g).reshape(B * (h1 - h0), s, 3)
        dst = p_i.gather(1, g).reshape(B * (h1 - h0), s, 3)
        T_h = umeyama_alignment(src, dst)[0].reshape(B, h1 - h0, 4, 4)  # batched Kabsch, p_i = T p_j
        R, t = T_h[..., :3, :3], T_h[..., :3, 3]
        f_h = torch.cat(
            [R.reshape(B, h1 - h0, 9), t, (R.transpose(-1, -2) @ t[..., None])[..., 0], (t * t).sum(-1, keepdim=True)], -1
        )  # (B, h, 16)
        counts = torch.empty(B, h1 - h0, dtype=torch.int64, device=dev)
        for c0 in range(0, h1 - h0, step):
            sq = torch.bmm(f_h[:, c0 : c0 + step], f_m)  # (B, h, Mc)
            if numpy_viewable(sq):  # NumPy counts a comparison's True entries about twice as fast
                counts[:, c0 : c0 + step] = torch.from_numpy(np.count_nonzero(sq.numpy() < limit.numpy()[:, None, :], axis=-1))
            else:
                counts[:, c0 : c0 + step] = (sq < limit[:, None, :]).sum(-1)
        good = ok[:, None] & torch.isfinite(T_h).flatten(-2).all(-1)
        counts = torch.where(good, counts, torch.full_like(counts, -1))
        top = counts.argmax(-1)  # first hypothesis of the block on ties
        top_count = counts.gather(1, top[:, None])[:, 0]
        better = ~done & (top_count > best_count)  # strictly: earlier blocks win ties
        best_count = torch.where(better, top_count, best_count)
        T = torch.where(better[:, None, None], T_h[rows, top], T)
        done = done | (_ransac_needed(best_count, num_candidates, s, cfg.ransac_confidence) <= h1)
        if host and h1 < H and bool(done.all()):
            break
    T = torch.where(ok[:, None, None], T, _eye4(p_i, B))
    inliers, _ = _inliers_at(p_i, p_j, valid & ok[:, None], T, cfg.inlier_threshold)
    return T, inliers


def ransac_rigid(
    p_i: Tensor,
    p_j: Tensor,
    valid: Tensor,
    cfg: SparseConfig | None = None,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Estimate rigid motions by RANSAC, all pairs and hypotheses at once.

    The minimal samples (:func:`ransac_samples`) are fitted by batched Kabsch calls and scored
    against every candidate of their pair by batched matrix products, a block of 50 hypotheses
    of every pair at a time; the hypothesis with the most inliers
    (``||R p_j + t - p_i|| / z < inlier_threshold``) wins, the first one on ties. A pair stops
    taking new hypotheses once the adaptive bound of ``cfg.ransac_confidence`` at its best
    inlier ratio is reached (all ``ransac_iterations`` at confidence 1); its result depends only
    on its own candidates.

    Args:
        p_i: (B, M, 3) points in frame i, metres.
        p_j: (B, M, 3) matching points in frame j, metres.
        valid: (B, M) bool candidate matches.
        cfg: RANSAC settings.
        generator: source of the base seed (``cfg.seed`` when None).

    Returns:
        T_ij: (B, 4, 4) best hypotheses (identity for a pair with fewer than ``ransac_sample``
            candidates).
        inliers: (B, M) bool inliers of ``T_ij`` among ``valid`` (none for such a pair).
    """
    dims: dict[str, int] = {}
    _check_corr(p_i, p_j, valid, dims)
    cfg = SparseConfig() if cfg is None else cfg
    idx, ok = _ransac_samples(valid, cfg, _base_seed(cfg, generator))
    return _ransac_from_samples(p_i, p_j.to(p_i.dtype), valid, idx, ok, cfg)


# ---------------------------------------------------------------------------- refinement


@functools.lru_cache(maxsize=8)
def _refine_maps(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Constant linear maps of the refinement's Gauss-Newton step.

    Returns:
        to_H: (16, 36) maps the weighted moments ``M = sum w [1, q] [1, q]^T`` (flattened 4 x 4:
            ``n``, ``Q = sum w q``, ``S = sum w q q^T``) to ``J^T W J`` (flattened 6 x 6) of
            ``J = [I, -[q]x]``: ``[[n I, -[Q]x], [[Q]x, tr(S) I - S]]``.
        to_hat: (6, 16) maps a twist ``(rho, phi)`` to its flattened 4 x 4 matrix ``[[phi]x, rho; 0, 0]``.
    """
    to_H = torch.zeros(4, 4, 6, 6, dtype=dtype, device=device)
    for a in range(3):
        to_H[0, 0, a, a] = 1.0  # n I
        for c in range(3):
            to_H[1 + c, 1 + c, 3 + a, 3 + a] += 1.0  # tr(S) I
            to_H[1 + a, 1 + c, 3 + a, 3 + c] -= 1.0  # -S
    # [Q]x = [[0, -Q2, Q1], [Q2, 0, -Q0], [-Q1, Q0, 0]]: lower-left block [Q]x, upper-right -[Q]x.
    for (row, col, k, sign) in ((0, 1, 2, -1), (0, 2, 1, 1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 0, 1, -1), (2, 1, 0, 1)):
        to_H[0, 1 + k, 3 + row, col] += sign
        to_H[0, 1 + k, row, 3 + col] -= sign
    to_hat = torch.zeros(6, 4, 4, dtype=dtype, device=device)
    for a in range(3):
        to_hat[a, a, 3] = 1.0
    for (row, col, k, sign) in ((0, 1, 2, -1), (0, 2, 1, 1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 0, 1, -1), (2, 1, 0, 1)):
        to_hat[3 + k, row, col] = sign
    return to_H.reshape(16, 36), to_hat.reshape(6, 16)


def _refine_rigid(p_i: Tensor, p_j: Tensor, mask: Tensor, T: Tensor, cfg: SparseConfig):
    if p_i.dtype == torch.float64 and all(numpy_viewable(x) for x in (p_i, p_j, mask, T)):
        return _refine_rigid_numpy(p_i, p_j, mask, T, cfg)
    # Few, large tensor operations per step (the pairs are small, so operation count sets the
    # time): one batched product for the residuals, one for all weighted moments, constant
    # linear maps for J^T W J and the twist's matrix, and the matrix exponential for exp(xi).
    B, M = mask.shape
    z = p_i[..., 2]
    inv_z2 = torch.where(mask, 1 / torch.where(mask, z * z, torch.ones_like(z)), torch.zeros_like(z))
    thr2 = torch.where(mask, (cfg.inlier_threshold * z) ** 2, torch.full_like(z, -1.0))  # never an inlier off mask
    delta2 = cfg.huber_delta**2
    to_H, to_hat = _refine_maps(p_i.dtype, p_i.device)
    ones = torch.ones_like(z)[..., None]
    for _ in range(cfg.refine_iterations):
        Rt = T[:, :3, :3].transpose(1, 2)
        q = torch.baddbmm(T[:, None, :3, 3], p_j, Rt)  # (B, M, 3) p_j moved into frame i by T
        r = q - p_i
        sq = (r * r).sum(-1)
        inl = sq < thr2
        # IRLS weights: Huber min(1, delta / e) on e = |r| / z, times 1 / z^2, on inliers only.
        w = torch.rsqrt((sq * inv_z2).clamp_min(delta2)).mul_(cfg.huber_delta * inv_z2 * inl)
        f = torch.cat([ones, q, r, torch.linalg.cross(q, r)], -1)  # (B, M, 10)
        G = torch.bmm((f * w[..., None]).transpose(1, 2), f[..., :4])  # (B, 10, 4) weighted moments
        Hm = (G[:, :4].reshape(B, 16) @ to_H).view(B, 6, 6)
        g = G[:, 4:, 0]  # [sum w r, sum w q x r] = J^T W r
        gn = solve_pair_steps(Hm, g, host=True)
        step = gn.delta * (gn.solved & (inl.sum(-1) >= 3))[:, None]
        T = torch.linalg.matrix_exp((step @ to_hat).view(B, 4, 4)) @ T
    inl, r = _inliers_at(p_i, p_j, mask, T, cfg.inlier_threshold)
    num = inl.sum(-1)
    sq = ((r * r).sum(-1) * inl).sum(-1)
    rmse = torch.where(num > 0, (sq / num.clamp_min(1)).sqrt(), torch.zeros_like(sq))
    return T, inl, rmse


def _refine_rigid_numpy(p_i: Tensor, p_j: Tensor, mask: Tensor, T: Tensor, cfg: SparseConfig):
    """:func:`_refine_rigid` in float64 NumPy (plain host tensors): the same steps, the 6 x 6
    solves as ``solve_pair_steps(host=True)`` and the exponential in closed form (equal to
    ``matrix_exp`` to round-off). A pair has a few hundred matches, so torch's fixed cost per
    operation was most of each step's time."""
    mk = mask.numpy()
    # Coordinates as planes (B, 3, M): every per-match operation reads contiguous rows.
    pi, pj = np.ascontiguousarray(p_i.numpy().transpose(0, 2, 1)), p_j.numpy().transpose(0, 2, 1)
    Tn = T.numpy()
    B, M = mk.shape
    z = pi[:, 2]
    inv_z2 = np.where(mk, 1 / np.where(mk, z * z, 1.0), 0.0)
    thr2 = np.where(mk, (cfg.inlier_threshold * z) ** 2, -1.0)  # never an inlier off mask
    delta2 = cfg.huber_delta**2
    scale = cfg.huber_delta * inv_z2
    to_H = _refine_maps(torch.float64, torch.device("cpu"))[0].numpy()
    f = np.empty((B, 10, M))  # rows [1, q, r, q x r]
    f[:, 0] = 1.0
    q, r = f[:, 1:4], f[:, 4:7]
    q0, q1, q2, r0, r1, r2 = f[:, 1], f[:, 2], f[:, 3], f[:, 4], f[:, 5], f[:, 6]
    for _ in range(cfg.refine_iterations):
        np.matmul(Tn[:, :3, :3], pj, out=q)
        q += Tn[:, :3, 3:]  # p_j moved into frame i by T
        np.subtract(q, pi, out=r)
        sq = r0 * r0
        sq += r1 * r1
        sq += r2 * r2
        inl = sq < thr2
        # IRLS weights: Huber min(1, delta / e) on e = |r| / z, times 1 / z^2, on inliers only.
        w = sq * inv_z2
        np.maximum(w, delta2, out=w)
        np.sqrt(w, out=w)
        np.divide(scale, w, out=w)
        w *= inl
        np.subtract(q1 * r2, q2 * r1, out=f[:, 7])
        np.subtract(q2 * r0, q0 * r2, out=f[:, 8])
        np.subtract(q0 * r1, q1 * r0, out=f[:, 9])
        G = (f * w[:, None]) @ f[:, :4].transpose(0, 2, 1)  # (B, 10, 4) weighted moments
        Hm = (G[:, :4].reshape(B, 16) @ to_H).reshape(B, 6, 6)
        gn = solve_pair_steps(torch.from_numpy(Hm), torch.from_numpy(np.ascontiguousarray(G[:, 4:, 0])), host=True)
        step = gn.delta.numpy() * (gn.solved.numpy() & (inl.sum(-1) >= 3))[:, None]
        Tn = se3_exp_numpy(step) @ Tn
    T_out = torch.from_numpy(Tn)
    inl, r = _inliers_at(p_i, p_j, mask, T_out, cfg.inlier_threshold)
    num = inl.sum(-1)
    sq = ((r * r).sum(-1) * inl).sum(-1)
    rmse = torch.where(num > 0, (sq / num.clamp_min(1)).sqrt(), torch.zeros_like(sq))
    return T_out, inl, rmse


def refine_rigid(
    p_i: Tensor,
    p_j: Tensor,
    mask: Tensor,
    T_init: Tensor,
    cfg: SparseConfig | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Refine rigid motions by Huber-weighted Gauss-Newton on SE(3), all pairs at once.

    Each of ``cfg.refine_iterations`` steps re-selects the inliers among ``mask`` at the current
    pose (``||R p_j + t - p_i|| / z < inlier_threshold``) and minimises
    ``sum_k huber(||R p_j^k + t - p_i^k|| / z_k)`` by one IRLS Gauss-Newton step with the left
    update ``T <- exp(xi) @ T``. A pair whose normal equations are singular (fewer than three
    inliers, degenerate geometry) keeps its pose.

    Args:
        p_i: (B, M, 3) points in frame i, metres.
        p_j: (B, M, 3) matching points in frame j, metres.
        mask: (B, M) bool candidate matches.
        T_init: (B, 4, 4) initial ``T_ij``.
        cfg: refinement settings.

    Returns:
        T: (B, 4, 4) refined ``T_ij`` in ``p_i``'s dtype.
        inliers: (B, M) bool inliers at ``T``.
        rmse: (B,) RMS of ``||R p_j + t - p_i||`` over those inliers, metres (0 without any).
    """
    dims: dict[str, int] = {}
    _check_corr(p_i, p_j, mask, dims)
    check_shape(T_init, "B 4 4", "T_init", dims)
    check_float(T_init, "T_init")
    cfg = SparseConfig() if cfg is None else cfg
    return _refine_rigid(p_i, p_j.to(p_i.dtype), mask, T_init.to(p_i.dtype), cfg)


# ---------------------------------------------------------------------------- registration


def _pad(rows: list[Tensor], width: int, fill: float = 0) -> Tensor:
    """Stack (K_b, *) tensors into (B, max(width, max K_b), *) padded with ``fill``."""
    out = pad_sequence(rows, batch_first=True, padding_value=fill)
    if out.shape[1] < width:
        more = out.new_full((out.shape[0], width - out.shape[1]) + tuple(out.shape[2:]), fill)
        out = torch.cat([out, more], 1)
    return out


def _match(fi: Sequence[FrameFeatures], fj: Sequence[FrameFeatures], cfg: SparseConfig, dev) -> Tensor:
    """(B, Kj_max) int64 index into frame i's keypoints of each frame-j keypoint, -1 = none.

    Only keypoints with valid depth take part; frame j's keypoints are the queries.
    """
    ki, kj = max(len(f) for f in fi), max(len(f) for f in fj)
    if ki == 0 or kj == 0:
        return torch.full((len(fi), kj), -1, dtype=torch.int64, device=dev)
    di = _pad([f.descriptors for f in fi], ki)
    dj = _pad([f.descriptors for f in fj], kj)
    vi = _pad([f.valid for f in fi], ki, False)
    vj = _pad([f.valid for f in fj], kj, False)
    return match_descriptors_batched(dj, di, vj, vi, max_distance=cfg.max_distance, backend=cfg.match_backend).index


def _check_features(f, name: str) -> None:
    if not isinstance(f, FrameFeatures):
        raise ShapeError(f"{name}: expected FrameFeatures, got {type(f).__name__}")


def _guided_index(
    pts_i: Tensor, valid_i: Tensor, desc_i: Tensor, xy_j: Tensor, valid_j: Tensor, desc_j: Tensor,
    T_pred: Tensor, focal: float, radius: float, max_distance: int,
) -> Tensor:
    """(B, Kj) int64 guided match of every frame-j keypoint into frame i's, -1 = none (see guided_match)."""
    B, Ki = valid_i.shape
    Kj = valid_j.shape[1]
    dev = pts_i.device
    none = torch.full((B, Kj), -1, dtype=torch.int64, device=dev)
    if Ki == 0 or Kj == 0:
        return none
    R, t = T_pred[:, :3, :3], T_pred[:, None, :3, 3]
    q = (pts_i - t) @ R  # (B, Ki, 3) frame-i points in frame j: p_j = R^T (p_i - t)
    if all(numpy_viewable(x) for x in (q, valid_i, desc_i, xy_j, valid_j, desc_j)):
        return torch.from_numpy(_guided_index_numpy(
            q.numpy(), valid_i.numpy(), desc_i.numpy(), xy_j.numpy(), valid_j.numpy(), desc_j.numpy(), focal, radius, max_distance
        ))
    z = q[..., 2]
    front = valid_i & (z > 1e-6)
    uv_i = focal * q[..., :2] / torch.where(front, z, torch.ones_like(z))[..., None]
    uv_j = focal * xy_j  # (B, Kj, 2), same normalised (undistorted) frame, scaled to pixels
    if not bool(valid_j.any()):
        return none
    # A grid of cells over frame j's keypoints, ``radius / _GUIDED_SPLIT`` wide, frame i's
    # keypoints sorted by cell (row-major). A query's window covers 2 k + 1 rows of cells; in each
    # row the cells it can reach are consecutive, hence one contiguous run of the sorted keypoints.
    big = torch.finfo(uv_j.dtype).max
    lo = torch.where(valid_j[..., None], uv_j, torch.full_like(uv_j, big)).amin(1).amin(0)  # (2,)
    hi = torch.where(valid_j[..., None], uv_j, torch.full_like(uv_j, -big)).amax(1).amax(0)
    k = _GUIDED_SPLIT
    cell = max(radius / k, float((hi - lo).max()) / _GUIDED_CELLS)
    k = max(1, math.ceil(radius / cell - 1e-9))  # rows of cells a window reaches on each side
    lo = lo - k * cell
    cells = ((hi - lo) / cell).floor().long() + k + 1  # (2,) columns, rows
    nx, ny = int(cells[0]), int(cells[1])
    per_pair = nx * ny
    ncell = B * per_pair
    ci = ((uv_i - lo) / cell).floor()
    inside = front & (ci >= 0).all(-1) & (ci[..., 0] < nx) & (ci[..., 1] < ny)
    ci = ci.clamp_min(0).long()
    pair = torch.arange(B, device=dev)[:, None]
    key_i = torch.where(inside, pair * per_pair + ci[..., 1] * nx + ci[..., 0], torch.full_like(ci[..., 0], ncell))
    key_i = key_i.reshape(-1)
    perm = torch.sort(key_i, stable=True).indices  # frame-i keypoints by cell, by index within one
    counts = torch.bincount(key_i, minlength=ncell + 1)
    ends = torch.cumsum(counts, 0)  # ends[c]: keypoints in cells < c + 1
    cj = ((uv_j - lo) / cell).floor().long().clamp(k, None)  # (B, Kj, 2); valid ones lie in [k, n - k - 1]
    # Row offset o reaches cells whose nearest point is (|o| - 1) cells away vertically, so its
    # columns span +- ceil(sqrt(r^2 - ((|o| - 1) cell)^2) / cell).
    off = torch.arange(-k, k + 1, device=dev)
    gap = ((off.abs() - 1).clamp_min(0) * cell).double()
    half = torch.ceil(torch.sqrt((radius * radius - gap * gap).clamp_min(0)) / cell - 1e-9).long()  # (2k+1,)
    row = (cj[..., 1, None] + off).clamp(0, ny - 1)  # (B, Kj, 2k+1)
    c0 = (cj[..., 0, None] - half).clamp(0, nx - 1)
    c1 = (cj[..., 0, None] + half).clamp(0, nx - 1)
    base = pair[..., None] * per_pair + row * nx
    start = torch.where(base + c0 > 0, ends.index_select(0, (base + c0 - 1).clamp_min(0).reshape(-1)).view_as(base), 0)
    cnt = ends.index_select(0, (base + c1).reshape(-1)).view_as(base) - start
    cnt = (cnt * valid_j[..., None]).reshape(-1)
    total = int(cnt.sum())
    if total == 0:
        return none
    # Frame i's positions, words and local indices in cell order, so a candidate's position in
    # the sorted list addresses them directly (one gather each, no detour through ``perm``).
    uv_s = index_select(uv_i.reshape(-1, 2), 0, perm)
    w_s = index_select(desc_i.reshape(-1, 32).contiguous().view(torch.int64), 0, perm)
    local_s = perm % Ki
    # Candidate p of run s sits at sorted position p - first[s] + start[s]; runs of one query are
    # consecutive, so its query is the run's query repeated over the run.
    runs = 2 * k + 1
    shift = start.reshape(-1) - (torch.cumsum(cnt, 0) - cnt)
    pos = torch.arange(total, device=dev) + repeat_counts(shift, cnt)
    query = repeat_counts(torch.arange(B * Kj, device=dev), cnt.view(-1, runs).sum(-1))
    d = index_select(uv_s, 0, pos) - index_select(uv_j.reshape(-1, 2), 0, query)
    d = d * d
    near = flat_nonzero(d[:, 0] + d[:, 1] <= radius * radius)
    pos, query = index_select(pos, 0, near), index_select(query, 0, near)
    w_j = desc_j.reshape(-1, 32).contiguous().view(torch.int64)
    dist = hamming_distance_indexed(w_j, query, w_s, pos)
    # Nearest candidate per query, the lowest frame-i index on ties (as brute force does).
    code = dist * Ki + index_select(local_s, 0, pos)
    best = torch.full((B * Kj,), (_BITS_MAX + 1) * Ki, dtype=torch.int64, device=dev)
    best.scatter_reduce_(0, query, code, reduce="amin")
    keep = (best // Ki) <= max_distance
    return torch.where(keep, best % Ki, torch.full_like(best, -1)).reshape(B, Kj)


def _guided_index_numpy(
    q: np.ndarray, valid_i: np.ndarray, desc_i: np.ndarray, xy_j: np.ndarray, valid_j: np.ndarray, desc_j: np.ndarray,
    focal: float, radius: float, max_distance: int,
) -> np.ndarray:
    """:func:`_guided_index` after the frame-i points are moved (``q``, (B, Ki, 3)), in NumPy on
    the host: the same cells, candidates and float64 arithmetic (so the same matches), the
    bits counted by ``hamming_distance_indexed`` and each query's nearest candidate taken by one segmented
    minimum (a query's candidates are consecutive) instead of a scatter. A few dozen operations
    on the candidate lists, where torch's fixed cost per operation was a large share."""
    B, Ki = valid_i.shape
    Kj = valid_j.shape[1]
    none = np.full((B, Kj), -1, dtype=np.int64)
    if not valid_j.any():
        return none
    z = q[..., 2]
    front = valid_i & (z > 1e-6)
    uv_i = focal * q[..., :2] / np.where(front, z, 1.0)[..., None]
    uv_j = focal * xy_j
    big = np.finfo(uv_j.dtype).max
    lo = np.where(valid_j[..., None], uv_j, big).min(1).min(0)  # (2,)
    hi = np.where(valid_j[..., None], uv_j, -big).max(1).max(0)
    k = _GUIDED_SPLIT
    cell = max(radius / k, float((hi - lo).max()) / _GUIDED_CELLS)
    k = max(1, math.ceil(radius / cell - 1e-9))
    lo = lo - k * cell
    cells = np.floor((hi - lo) / cell).astype(np.int64) + k + 1
    nx, ny = int(cells[0]), int(cells[1])
    per_pair = nx * ny
    ncell = B * per_pair
    ci = np.floor((uv_i - lo) / cell)
    inside = front & (ci >= 0).all(-1) & (ci[..., 0] < nx) & (ci[..., 1] < ny)
    ci = np.maximum(ci, 0).astype(np.int64)
    pair = np.arange(B)[:, None]
    key_i = np.where(inside, pair * per_pair + ci[..., 1] * nx + ci[..., 0], ncell).reshape(-1)
    perm = np.argsort(key_i, kind="stable")
    ends = np.cumsum(np.bincount(key_i, minlength=ncell + 1))
    cj = np.maximum(np.floor((uv_j - lo) / cell).astype(np.int64), k)
    off = np.arange(-k, k + 1)
    gap = np.maximum(np.abs(off) - 1, 0) * cell
    half = np.ceil(np.sqrt(np.maximum(radius * radius - gap * gap, 0)) / cell - 1e-9).astype(np.int64)
    row = np.clip(cj[..., 1, None] + off, 0, ny - 1)  # (B, Kj, 2k+1)
    c0 = np.clip(cj[..., 0, None] - half, 0, nx - 1)
    c1 = np.clip(cj[..., 0, None] + half, 0, nx - 1)
    base = pair[..., None] * per_pair + row * nx
    start = np.where(base + c0 > 0, np.take(ends, np.maximum(base + c0 - 1, 0)), 0)
    cnt = ((np.take(ends, base + c1) - start) * valid_j[..., None]).reshape(-1)
    total = int(cnt.sum())
    if total == 0:
        return none
    # Row gathers by np.take: several times faster than fancy indexing for rows of a few numbers.
    uv_s = np.take(uv_i.reshape(-1, 2), perm, axis=0)
    w_s = np.take(np.ascontiguousarray(desc_i.reshape(-1, 32)).view(np.int64), perm, axis=0)
    local_s = perm % Ki
    runs = 2 * k + 1
    shift = start.reshape(-1) - (np.cumsum(cnt) - cnt)
    pos = np.arange(total) + np.repeat(shift, cnt)
    query = np.repeat(np.arange(B * Kj), cnt.reshape(-1, runs).sum(-1))
    d = np.take(uv_s, pos, axis=0) - np.take(uv_j.reshape(-1, 2), query, axis=0)
    d *= d
    near = np.flatnonzero(d[:, 0] + d[:, 1] <= radius * radius)
    if not len(near):
        return none
    pos, query = np.take(pos, near), np.take(query, near)
    w_j = np.ascontiguousarray(desc_j.reshape(-1, 32)).view(np.int64)
    t = torch.from_numpy  # the arrays' memory, no copies
    dist = hamming_distance_indexed(t(w_j), t(query), t(w_s), t(pos)).numpy()
    # Nearest candidate per query, the lowest frame-i index on ties (as brute force does).
    code = dist * Ki + np.take(local_s, pos)
    first = np.flatnonzero(np.r_[True, query[1:] != query[:-1]])  # query is sorted: runs of one query
    best = np.minimum.reduceat(code, first)
    out = none.reshape(-1)
    keep = best // Ki <= max_distance
    out[query[first[keep]]] = best[keep] % Ki
    return out.reshape(B, Kj)


def _prediction_shift(res: SparseResult, T_pred: Tensor, focal: float) -> Tensor:
    """(B,) mean distance in pixels between the inliers' frame-i points projected by ``T_pred`` and by ``res.T_ij``."""
    inl = res.inliers
    p = res.points_i

    def project(T: Tensor) -> Tensor:
        q = (p - T[:, None, :3, 3]) @ T[:, :3, :3]
        z = q[..., 2:]
        return q[..., :2] / torch.where(inl[..., None] & (z > 1e-6), z, torch.ones_like(z))

    d = (project(T_pred) - project(res.T_ij)).norm(dim=-1) * focal
    n = inl.sum(-1)
    return (d * inl).sum(-1) / n.clamp_min(1)  # 0 without inliers


def _padded_inputs(fi: Sequence[FrameFeatures], fj: Sequence[FrameFeatures]):
    ki, kj = max(len(f) for f in fi), max(len(f) for f in fj)
    pts_i = _pad([f.points.to(torch.float64) for f in fi], ki)
    pts_j = _pad([f.points.to(torch.float64) for f in fj], kj)
    vi = _pad([f.valid for f in fi], ki, False)
    vj = _pad([f.valid for f in fj], kj, False)
    di = _pad([f.descriptors for f in fi], ki)
    dj = _pad([f.descriptors for f in fj], kj)
    return pts_i, vi, di, pts_j, vj, dj


def _check_pairs(fi, fj) -> None:
    if isinstance(fi, FrameFeatures) or isinstance(fj, FrameFeatures):
        raise ShapeError("fi/fj: expected sequences of FrameFeatures (use register_sparse for one pair)")
    if len(fi) != len(fj):
        raise ShapeError(f"fj: expected {len(fi)} FrameFeatures like fi, got {len(fj)}")
    if len(fi) == 0:
        raise ShapeError("fi: expected at least one pair, got none")
    for b in range(len(fi)):
        _check_features(fi[b], f"fi[{b}]")
        _check_features(fj[b], f"fj[{b}]")


def _check_prediction(T_pred: Tensor, B: int, focal) -> None:
    check_shape(T_pred, f"{B} 4 4", "T_pred")
    check_float(T_pred, "T_pred")
    if focal is None or not focal > 0:
        raise ConfigError(f"focal: expected a positive focal length in pixels with T_pred, got {focal}")


def guided_match(
    fi: Sequence[FrameFeatures],
    fj: Sequence[FrameFeatures],
    T_pred: Tensor,
    focal: float,
    radius: float,
    max_distance: int = 50,
) -> Tensor:
    """Match frame-j keypoints to frame-i keypoints near their predicted positions, B pairs at once.

    Frame i's 3-D points are moved into frame j by the predicted ``T_pred`` (``p_i = T p_j``)
    and projected; each frame-j keypoint with valid depth takes the nearest descriptor (Hamming,
    the lowest index on ties, within ``max_distance`` bits) among the frame-i keypoints with
    valid depth whose projection lies within ``radius`` pixels of it. Positions are compared in
    undistorted normalised coordinates scaled by ``focal``, so lens distortion does not bias the
    window. A grid of ``radius``-sized cells finds the candidates (a sort and a bincount, no
    loop over keypoints); with a window that covers every keypoint the result is the
    brute-force match's.

    Args:
        fi: B reference (keyframe) features, frame i.
        fj: B current-frame features, frame j.
        T_pred: (B, 4, 4) predicted ``T_ij``.
        focal: focal length in pixels that scales normalised coordinates to pixels.
        radius: window radius, pixels (> 0).
        max_distance: largest accepted Hamming distance, bits.

    Returns:
        (B, Kj_max) int64 index into frame i's keypoints of each frame-j keypoint, -1 = none.
    """
    _check_pairs(fi, fj)
    _check_prediction(T_pred, len(fi), focal)
    if not radius > 0:
        raise ConfigError(f"radius: expected a positive window in pixels, got {radius}")
    pts_i, vi, di, pts_j, vj, dj = _padded_inputs(fi, fj)
    return _guided_from_padded(pts_i, vi, di, pts_j, vj, dj, T_pred, focal, radius, max_distance)


def _guided_from_padded(pts_i, vi, di, pts_j, vj, dj, T_pred, focal, radius, max_distance) -> Tensor:
    zj = pts_j[..., 2]
    xy_j = pts_j[..., :2] / torch.where(vj, zj, torch.ones_like(zj))[..., None]
    return _guided_index(pts_i, vi, di, xy_j, vj, dj, T_pred.to(torch.float64), float(focal), float(radius), max_distance)


def _register_index(
    fi, fj, index: Tensor, cfg: SparseConfig, seed: int, pts_i: Tensor, pts_j: Tensor,
    T_init: Tensor | None = None, init: Tensor | None = None,
) -> SparseResult:
    """Isometry filter, RANSAC and refinement of the matches ``index`` (B, Kj) of B pairs.

    Pairs where ``init`` (B,) bool is True skip the filter and RANSAC: their refinement starts at
    ``T_init`` (B, 4, 4), a pose already found for them, and selects its inliers among all
    matches (the others' results do not change).
    """
    dev = pts_i.device
    B = len(fi)
    has = index >= 0
    num_matches = has.sum(-1)
    M = int(num_matches.max()) if index.numel() else 0
    order = torch.argsort((~has).to(torch.int8), dim=-1, stable=True)[:, :M]  # matched j first
    valid = has.gather(1, order)  # (B, M)
    kj = max(1, index.shape[1])
    pts_i = pts_i if pts_i.shape[1] else pts_i.new_zeros(B, 1, 3)
    pts_j = pts_j if pts_j.shape[1] >= kj else _pad([f.points.to(torch.float64) for f in fj], kj)
    pix_j = _pad([f.keypoints.to(torch.float32) for f in fj], kj)
    zero = torch.zeros((), dtype=torch.float64, device=dev)
    row_i = index.gather(1, order).clamp_min(0)
    p_i = torch.where(valid[..., None], pts_i.gather(1, row_i[..., None].expand(-1, -1, 3)), zero)
    p_j = torch.where(valid[..., None], pts_j.gather(1, order[..., None].expand(-1, -1, 3)), zero)
    pixels_j = torch.where(valid[..., None], pix_j.gather(1, order[..., None].expand(-1, -1, 2)), zero.float())

    if init is None or not bool(init.all()):
        filtered = _isometry_filter(p_i, p_j, valid, cfg, seed)
        idx, ok = _ransac_samples(filtered, cfg, seed)
        T0, _ = _ransac_from_samples(p_i, p_j, filtered, idx, ok, cfg)
    else:
        filtered, ok, T0 = valid, num_matches >= cfg.ransac_sample, T_init
    if init is not None:
        filtered = torch.where(init[:, None], valid, filtered)
        ok = torch.where(init, num_matches >= cfg.ransac_sample, ok)
        T0 = torch.where(init[:, None, None], T_init.to(T0.dtype), T0)
    T, inliers, rmse = _refine_rigid(p_i, p_j, filtered & ok[:, None], T0, cfg)
    finite = torch.isfinite(T).flatten(-2).all(-1)
    T = torch.where(finite[:, None, None], T, _eye4(T, B))
    inliers = inliers & finite[:, None]
    rmse = torch.where(finite, rmse, torch.zeros_like(rmse))
    num_inliers = inliers.sum(-1)
    success = ok & finite & (num_inliers >= cfg.min_inliers)
    z = p_i[..., 2]
    weights = torch.where(inliers, 1 / torch.where(inliers, z * z, torch.ones_like(z)), torch.zeros_like(z))
    stats = PairStats.from_padded(p_i, p_j, mask=inliers, weights=weights)
    logger.debug(
        "register_sparse_batch: matches %s filtered %s inliers %s",
        num_matches.tolist(), filtered.sum(-1).tolist(), num_inliers.tolist(),
    )
    return SparseResult(
        T_ij=T,
        success=success,
        num_matches=num_matches,
        num_filtered=filtered.sum(-1),
        num_inliers=num_inliers,
        points_i=p_i,
        points_j=p_j,
        inliers=inliers,
        weights=weights,
        rmse=rmse,
        stats=stats,
        pixels_j=pixels_j,
        guided=torch.zeros(B, dtype=torch.bool, device=dev),
    )


def register_sparse_batch(
    fi: Sequence[FrameFeatures],
    fj: Sequence[FrameFeatures],
    cfg: SparseConfig | None = None,
    generator: torch.Generator | None = None,
    T_pred: Tensor | None = None,
    focal: float | None = None,
) -> SparseResult:
    """Register B frame pairs: match, isometry filter, RANSAC and refinement, batched.

    Matching runs per pair on the CPU (one int8 GEMM or OpenCV, whichever is faster there) and for all pairs at once in
    torch elsewhere (``cfg.match_backend``); the matches are padded to a common length and every
    later stage runs on the whole batch with masks. Failure (too few matches or inliers) is reported in
    ``success``, never raised; poses stay finite.

    With a prediction ``T_pred`` and ``cfg.guided_radius > 0`` the matches are guided
    (:func:`guided_match`); a pair whose guided registration fails or keeps fewer than
    ``cfg.guided_min_inliers`` inliers, or fewer than ``cfg.guided_min_fraction`` of the keypoints
    with depth, is matched again by brute force and registered again with the same random
    choices, and that result is kept where the guided one failed or kept fewer inliers
    (``guided`` says which pairs kept their guided result); one
    whose pose moves its inliers' projections by more than half the window (on average) from
    the predicted ones is first matched again guided by that pose.

    Args:
        fi: B reference (keyframe) features, frame i.
        fj: B current-frame features, frame j.
        cfg: registration settings.
        generator: source of the base seed (``cfg.seed`` when None); every pair uses the same
            base seed, so the result of a pair does not depend on the rest of the batch.
        T_pred: optional (B, 4, 4) predicted ``T_ij`` for guided matching.
        focal: focal length in pixels (the guided window's scale); needed with ``T_pred``.

    Returns:
        The registrations of the B pairs, ``T_ij`` with ``p_i = T_ij p_j``.

    Raises:
        ShapeError: ``fi`` and ``fj`` differ in length, are empty, or hold something else; a
            ``T_pred`` that is not (B, 4, 4).
        ConfigError: ``T_pred`` without a positive ``focal``.
    """
    _check_pairs(fi, fj)
    cfg = SparseConfig() if cfg is None else cfg
    B = len(fi)
    guide = T_pred is not None and cfg.guided_radius > 0
    if T_pred is not None:
        _check_prediction(T_pred, B, focal)
    dev = fi[0].points.device
    seed = _base_seed(cfg, generator)
    if not guide:
        pts_i = _pad([f.points.to(torch.float64) for f in fi], max(1, max(len(f) for f in fi)))
        pts_j = _pad([f.points.to(torch.float64) for f in fj], max(1, max(len(f) for f in fj)))
        return _register_index(fi, fj, _match(fi, fj, cfg, dev), cfg, seed, pts_i, pts_j)
    pts_i, vi, di, pts_j, vj, dj = _padded_inputs(fi, fj)
    index = _guided_from_padded(pts_i, vi, di, pts_j, vj, dj, T_pred, focal, cfg.guided_radius, cfg.max_distance)
    res = _register_index(fi, fj, index, cfg, seed, pts_i, pts_j)
    # Inliers needed to keep a guided result: guided_min_inliers, and guided_min_fraction of the
    # keypoints with depth of the frame with fewer.
    need = torch.maximum(torch.full((B,), float(cfg.guided_min_inliers), dtype=torch.float64, device=dev),
                         cfg.guided_min_fraction * torch.minimum(vi.sum(-1), vj.sum(-1)).to(torch.float64))
    weak = ~res.success | (res.num_inliers < need)
    shifted = ~weak & (_prediction_shift(res, T_pred.to(torch.float64), float(focal)) > _GUIDED_MAX_SHIFT * cfg.guided_radius)
    if bool(shifted.any()):
        # The prediction was off by much of the window: match again around the pose just found
        # (which true matches the first window cut off now fall inside) and refine from that
        # pose (no filter or RANSAC: the pose is RANSAC's already), then judge as before.
        again = _guided_from_padded(pts_i, vi, di, pts_j, vj, dj, res.T_ij, focal, cfg.guided_radius, cfg.max_distance)
        index = torch.where(shifted[:, None], again, index)
        res = _register_index(fi, fj, index, cfg, seed, pts_i, pts_j, T_init=res.T_ij, init=shifted)
        weak = ~res.success | (res.num_inliers < need)
    if not bool(weak.any()):
        res.guided = torch.ones(B, dtype=torch.bool, device=dev)
        return res
    # Only the weak pairs are matched and registered again: the others keep their guided result
    # (a pair's result does not depend on the rest of the batch).
    redo = weak.nonzero().flatten().tolist()
    fi_redo, fj_redo = [fi[b] for b in redo], [fj[b] for b in redo]
    rows = torch.tensor(redo, device=dev)
    brute = _match(fi_redo, fj_redo, cfg, dev)
    again = _register_index(fi_redo, fj_redo, brute, cfg, seed, pts_i[rows], pts_j[rows])
    # Brute force replaces a failed guided result, and a weak one where it keeps more inliers (a
    # right guided registration with few inliers often holds more than brute force finds).
    take = ~res.success[rows] | (again.success & (again.num_inliers > res.num_inliers[rows]))
    res = _put_rows(res, rows[take], _rows(again, take))
    res.guided = torch.ones(B, dtype=torch.bool, device=dev)
    res.guided[rows[take]] = False
    return res


# The (B, M, ...) fields of a SparseResult, padded along M with zeros (False) past its matches.
_PADDED_FIELDS = frozenset({"points_i", "points_j", "inliers", "weights", "pixels_j"})


def _rows(res: SparseResult, keep: Tensor) -> SparseResult:
    """The pairs of ``res`` where ``keep`` (B,) bool is True."""
    stats = PairStats(**{f.name: getattr(res.stats, f.name)[keep] for f in fields(PairStats)})
    values = {f.name: getattr(res, f.name)[keep] for f in fields(SparseResult) if f.name not in ("stats", "guided")}
    return SparseResult(**values, stats=stats, guided=None if res.guided is None else res.guided[keep])


def _put_rows(res: SparseResult, rows: Tensor, sub: SparseResult) -> SparseResult:
    """``res`` with its rows ``rows`` (R,) replaced by the R pairs of ``sub``.

    The padded (B, M, ...) fields take the wider of the two paddings.
    """

    def put(a: Tensor, b: Tensor, padded: bool) -> Tensor:
        if padded and a.shape[1] != b.shape[1]:
            width = max(a.shape[1], b.shape[1])
            a, b = (torch.cat([x, x.new_zeros(x.shape[0], width - x.shape[1], *x.shape[2:])], dim=1) for x in (a, b))
        out = a.clone()
        out[rows] = b
        return out

    stats = PairStats(**{f.name: put(getattr(res.stats, f.name), getattr(sub.stats, f.name), False) for f in fields(PairStats)})
    values = {
        f.name: put(getattr(res, f.name), getattr(sub, f.name), f.name in _PADDED_FIELDS)
        for f in fields(SparseResult) if f.name not in ("stats", "guided")
    }
    return SparseResult(**values, stats=stats, guided=res.guided)


def register_sparse(
    fi: FrameFeatures,
    fj: FrameFeatures,
    cfg: SparseConfig | None = None,
    generator: torch.Generator | None = None,
) -> SparseResult:
    """Register one frame pair (B = 1); see :func:`register_sparse_batch`.

    Args:
        fi: reference (keyframe) features, frame i.
        fj: current-frame features, frame j.
        cfg: registration settings.
        generator: source of the base seed (``cfg.seed`` when None).

    Returns:
        A :class:`SparseResult` with B = 1, ``T_ij`` mapping frame-j points into frame i.
    """
    _check_features(fi, "fi")
    _check_features(fj, "fj")
    return register_sparse_batch([fi], [fj], cfg, generator)
