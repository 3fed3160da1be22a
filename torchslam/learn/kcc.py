"""NI-SLAM front-end training objective: image-plane translation of keyframe/frame pairs.

A pair is a keyframe and a frame some steps later. Exactly as ``kcc.frontend.track_step`` does,
the keyframe's own cloud is projected orthographically at the resolution ``r_k`` chosen for it
(``choose_resolution``), the frame's cloud is rotated into the keyframe's attitude
(``R_wk^T R_wi``, here from ground truth) and projected at the same ``r_k``, and both become
KCC channels (``kcc_channels``). None of that depends on σ, λ or the soft arg-max temperature,
so it is computed once (:class:`KCCPairs`); a training step only trains the correlators on the
keyframe channels, correlates the frames and takes the soft arg-max, all batched over pairs.

Convention:
    Poses are camera-to-world. The scene content of the frame moved by ``t`` in the keyframe
    attitude frame and the frame's camera sits at ``-t`` (``NISlam._pose``), so the ground truth
    is ``t = -R_wk^T (p_wi - p_wk)`` and its first two components are the image-plane
    translation ``t_xy`` that ``kcc_predict`` estimates as ``r_k * shift``.

The loss is the mean squared error of the predicted ``t_xy`` in pixels of the keyframe's
orthographic image, ``|(t_xy - t_xy_gt) / r_k|²``: the KCC works in pixels, and pairs of
keyframes with different resolutions then count alike.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ConfigError, ShapeError, check_float, check_shape
from ..geometry import undistorted_rays
from ..kcc import (
    KCCConfig,
    OrthoImages,
    choose_resolution,
    kcc_channels,
    kcc_predict,
    kcc_train,
    orthographic_project,
    rgbd_to_points,
    sample_grey,
)

__all__ = [
    "KCCLoss",
    "KCCPairs",
    "content_translation",
    "kcc_pair_errors",
    "kcc_pairs_from_points",
    "kcc_shift_loss",
    "ortho_pairs_from_points",
    "resized_kcc_config",
    "synthetic_kcc_pairs",
    "tum_kcc_pairs",
]

# Synthetic trajectories cycled over seeds: hand-held pan, sideways slide, room loop, orbit.
TRAJECTORIES = ("handheld", "translate", "loop", "orbit")


@dataclass(frozen=True)
class KCCPairs:
    """Keyframe/frame pairs ready for the correlator, with ground truth.

    Attributes:
        keyframe: (B, 2, H, W) KCC channels of the keyframes' orthographic images.
        frame: (B, 2, H, W) KCC channels of the frames, rotated into the keyframe attitude and
            projected at the keyframe's resolution.
        resolution: (B,) keyframe resolutions ``r_k``, metres per pixel.
        t_xy: (B, 2) true image-plane content translation in the keyframe attitude frame, metres.
    """

    keyframe: Tensor
    frame: Tensor
    resolution: Tensor
    t_xy: Tensor

    def __post_init__(self) -> None:
        d: dict[str, int] = {}
        check_shape(self.keyframe, "B C H W", "keyframe", d)
        check_shape(self.frame, "B C H W", "frame", d)
        check_shape(self.resolution, "B", "resolution", d)
        check_shape(self.t_xy, "B 2", "t_xy", d)
        for name in ("keyframe", "frame", "resolution", "t_xy"):
            check_float(getattr(self, name), name)

    def __len__(self) -> int:
        return self.keyframe.shape[0]

    def select(self, index: Tensor | slice) -> "KCCPairs":
        """Return the pairs at ``index`` (a slice, (K,) int64 indices or a (B,) bool mask)."""
        return KCCPairs(self.keyframe[index], self.frame[index], self.resolution[index], self.t_xy[index])

    @staticmethod
    def cat(parts: Sequence["KCCPairs"]) -> "KCCPairs":
        """Concatenate pair sets of the same image size."""
        if not parts:
            raise ShapeError("parts: expected at least one KCCPairs, got none")
        return KCCPairs(*(torch.cat([getattr(p, f) for p in parts]) for f in ("keyframe", "frame", "resolution", "t_xy")))


def content_translation(T_wk: Tensor, T_wi: Tensor) -> Tensor:
    """Return the true scene-content translation of frames relative to their keyframes.

    Convention:
        ``t = -R_wk^T (p_wi - p_wk)``: the frame's camera sits at ``-t`` in the keyframe's
        attitude frame (``NISlam._pose``); ``t[..., :2]`` is the image-plane part ``t_xy``.

    Args:
        T_wk: (..., 4, 4) keyframe poses, camera to world.
        T_wi: (..., 4, 4) frame poses, camera to world.

    Returns:
        (..., 3) translation in the keyframe attitude frame, metres.
    """
    check_shape(T_wk, "... 4 4", "T_wk")
    check_shape(T_wi, "... 4 4", "T_wi")
    d = (T_wi[..., :3, 3] - T_wk[..., :3, 3])[..., None]
    return -(T_wk[..., :3, :3].transpose(-1, -2) @ d)[..., 0]


def kcc_pairs_from_points(
    points_k: Tensor,
    grey_k: Tensor,
    valid_k: Tensor,
    points_i: Tensor,
    grey_i: Tensor,
    valid_i: Tensor,
    T_wk: Tensor,
    T_wi: Tensor,
    cfg: KCCConfig,
) -> KCCPairs:
    """Build KCC pairs from camera-frame clouds and poses (NI-SLAM §4, as ``track_step`` does).

    Args:
        points_k: (B, N, 3) keyframe clouds, camera frame, metres.
        grey_k: (B, N) keyframe grey values.
        valid_k: (B, N) bool.
        points_i: (B, N, 3) frame clouds.
        grey_i: (B, N) frame grey values.
        valid_i: (B, N) bool.
        T_wk: (B, 4, 4) keyframe poses (the rotation gives the attitude, the translation the truth).
        T_wi: (B, 4, 4) frame poses.
        cfg: orthographic size, coverage, sampling, channel normalisation and hole filling.

    Returns:
        KCCPairs in the dtype of the points.
    """
    kf, fr, t = ortho_pairs_from_points(points_k, grey_k, valid_k, points_i, grey_i, valid_i, T_wk, T_wi, cfg)
    return KCCPairs(kcc_channels(kf, cfg), kcc_channels(fr, cfg, frame=True), kf.resolution, t)


def resized_kcc_config(cfg: KCCConfig, ortho_height: int, ortho_width: int, **changes) -> KCCConfig:
    """``cfg`` at another orthographic size, its ``frame_taper`` scaled with the image.

    Training renders smaller orthographic images than a run (``KCCTrainConfig``'s 180×240
    against NI-SLAM's 360×480) of the same scene extent (``choose_resolution`` picks ``r_k`` from
    the size and ``coverage``), so the frame's border taper keeps its share of the window and of
    the scene: ``round(frame_taper * min(ortho_height / H, ortho_width / W))`` pixels, at least 1
    where the run tapers at all.

    Args:
        cfg: the run's settings (e.g. ``NISlamConfig().kcc``).
        ortho_height: orthographic image height of the training pairs.
        ortho_width: orthographic image width.
        **changes: further fields to replace.
    """
    taper = cfg.frame_taper
    if taper:
        scale = min(ortho_height / cfg.ortho_height, ortho_width / cfg.ortho_width)
        taper = max(1, round(taper * scale))
    return dataclasses.replace(cfg, ortho_height=ortho_height, ortho_width=ortho_width, frame_taper=taper, **changes)


def ortho_pairs_from_points(
    points_k: Tensor,
    grey_k: Tensor,
    valid_k: Tensor,
    points_i: Tensor,
    grey_i: Tensor,
    valid_i: Tensor,
    T_wk: Tensor,
    T_wi: Tensor,
    cfg: KCCConfig,
) -> tuple[OrthoImages, OrthoImages, Tensor]:
    """The orthographic images behind ``kcc_pairs_from_points`` (same arguments), before any channels.

    Returns:
        The keyframes' images (at the resolution chosen for them), the frames' images (rotated
        into the keyframes' attitude, same resolution) and the (B, 2) true ``t_xy``, metres.
    """
    d: dict[str, int] = {}
    check_shape(points_k, "B N 3", "points_k", d)
    check_shape(points_i, "B N 3", "points_i", d)
    check_shape(T_wk, "B 4 4", "T_wk", d)
    check_shape(T_wi, "B 4 4", "T_wi", d)
    size = (cfg.ortho_height, cfg.ortho_width)
    r = choose_resolution(points_k, valid_k, size, cfg.coverage, cfg.sample_step)
    kf = orthographic_project(points_k, grey_k, valid_k, None, r, size)
    R_ki = (T_wk[:, :3, :3].transpose(1, 2) @ T_wi[:, :3, :3]).to(points_i.dtype)
    fr = orthographic_project(points_i, grey_i, valid_i, R_ki, r, size)
    t = content_translation(T_wk.to(torch.float64), T_wi.to(torch.float64))[:, :2].to(points_k.dtype)
    return kf, fr, t


def _pair_indices(frames: int, keyframe_step: int, gaps: Sequence[int]) -> tuple[list[int], list[int]]:
    starts, ends = [], []
    for n, k in enumerate(range(0, frames, keyframe_step)):
        g = gaps[n % len(gaps)]
        if k + g < frames:
            starts.append(k)
            ends.append(k + g)
    return starts, ends


def _check_gaps(gaps: Sequence[int], keyframe_step: int) -> list[int]:
    gaps = list(gaps)
    if not gaps or not all(isinstance(g, int) and g >= 1 for g in gaps):
        raise ConfigError(f"gaps: expected positive frame steps, got {gaps!r}")
    if not (isinstance(keyframe_step, int) and keyframe_step >= 1):
        raise ConfigError(f"keyframe_step: expected a positive int, got {keyframe_step!r}")
    return gaps


def synthetic_kcc_pairs(
    seeds: Sequence[int],
    cfg: KCCConfig,
    frames: int = 60,
    keyframe_step: int = 5,
    gaps: Sequence[int] = (2, 4, 6, 8),
    width: int = 320,
    height: int = 240,
    trajectories: Sequence[str] = TRAJECTORIES,
) -> KCCPairs:
    """Render keyframe/frame pairs from synthetic sequences with exact ground truth.

    Sequence ``seed`` uses trajectory ``trajectories[seed % len(trajectories)]``; its keyframes
    are frames ``0, keyframe_step, ...`` and the frame of keyframe ``n`` is ``gaps[n % len(gaps)]``
    frames later. Depth carries the generator's Kinect-like noise and holes (seeded per frame).

    Args:
        seeds: sequence seeds (training and validation use disjoint ones).
        cfg: KCC settings (orthographic size etc.).
        frames: frames per sequence (at 30 Hz).
        keyframe_step: frames between consecutive keyframes.
        gaps: frame steps from a keyframe to its frame.
        width: rendered image width, pixels.
        height: rendered image height, pixels.
        trajectories: trajectory kinds to cycle over.

    Returns:
        KCCPairs in float32.
    """
    from ..data.synthetic import SyntheticConfig, generate_sequence

    gaps = _check_gaps(gaps, keyframe_step)
    if not seeds:
        raise ConfigError("seeds: expected at least one sequence seed, got none")
    parts = []
    for seed in seeds:  # one sequence (scene) per seed: data set-up, not a hot path
        scfg = SyntheticConfig(frames=frames, width=width, height=height, seed=int(seed),
                               trajectory=trajectories[int(seed) % len(trajectories)])
        seq = generate_sequence(scfg)
        starts, ends = _pair_indices(frames, keyframe_step, gaps)
        rgb, depth = seq.render(starts + ends)
        intr = seq.camera.as_tensor(torch.float32)
        points, grey, valid = rgbd_to_points(rgb, depth, intr)
        B = len(starts)
        T = seq.groundtruth.T_wc
        parts.append(kcc_pairs_from_points(points[:B], grey[:B], valid[:B], points[B:], grey[B:], valid[B:],
                                           T[starts], T[ends], cfg))
    return KCCPairs.cat(parts)


def tum_kcc_pairs(
    folder: str | os.PathLike,
    cfg: KCCConfig,
    first: int = 0,
    count: int = 40,
    keyframe_step: int = 5,
    gaps: Sequence[int] = (2, 4, 6, 8),
) -> KCCPairs:
    """Keyframe/frame pairs of a TUM-layout sequence with ground truth (geometry at the depth instants).

    As ``NISlam`` does: the clouds are back-projected along the undistorted rays, each point's
    grey value is sampled where it appears in the colour image after the (ground-truth)
    rotation between the depth and colour instants, and the poses are the ground truth
    interpolated at the depth timestamps.

    Args:
        folder: sequence folder with ``groundtruth.txt``.
        cfg: KCC settings.
        first: first frame used.
        count: frames used from ``first``.
        keyframe_step: frames between keyframes.
        gaps: frame steps from a keyframe to its frame.

    Returns:
        KCCPairs in float32 (pairs whose poses the ground truth does not cover are left out).
    """
    from ..data.tum import TUMSequence

    gaps = _check_gaps(gaps, keyframe_step)
    seq = TUMSequence(folder, prefetch=0)
    if seq.groundtruth is None:
        raise ConfigError(f"{folder}: the sequence has no groundtruth.txt to train or validate against")
    last = min(len(seq), first + count)
    starts, ends = _pair_indices(last - first, keyframe_step, gaps)
    idx = sorted(set(starts) | set(ends))
    frames = {i: seq[first + i] for i in idx}  # decoding files: data set-up
    rgb = torch.stack([frames[i].rgb for i in idx])
    depth = torch.stack([frames[i].depth for i in idx])
    t_depth = torch.tensor([frames[i].geometry_time for i in idx], dtype=torch.float64)
    t_rgb = torch.tensor([frames[i].timestamp for i in idx], dtype=torch.float64)
    T_d, ok_d = seq.groundtruth.interpolate(t_depth, max_gap=0.1)
    T_c, ok_c = seq.groundtruth.interpolate(t_rgb, max_gap=0.1)
    cam = seq.camera
    intr = cam.as_tensor(torch.float32)[None].expand(len(idx), 4)
    rays = undistorted_rays(cam, torch.float32) if cam.has_distortion else None
    points, grey, valid = rgbd_to_points(rgb, depth, intr, rays=rays)
    R_cd = (T_c[:, :3, :3].transpose(1, 2) @ T_d[:, :3, :3]).to(torch.float32)
    grey, valid = sample_grey(rgb, points, valid, R_cd, intr, grey_image=grey,
                              distortion=cam.distortion if cam.has_distortion else None)
    pos = {i: n for n, i in enumerate(idx)}
    a = torch.tensor([pos[i] for i in starts], dtype=torch.int64)
    b = torch.tensor([pos[i] for i in ends], dtype=torch.int64)
    keep = ok_d[a] & ok_d[b] & ok_c[a] & ok_c[b]
    a, b = a[keep], b[keep]
    if a.numel() == 0:
        raise ConfigError(f"{folder}: no frame pair in frames {first}..{last - 1} is covered by the ground truth")
    return kcc_pairs_from_points(points[a], grey[a], valid[a], points[b], grey[b], valid[b], T_d[a], T_d[b], cfg)


@dataclass(frozen=True)
class KCCLoss:
    """Soft arg-max translation loss of a batch of pairs.

    Attributes:
        loss: 0-d mean over pairs of the squared error in pixels, differentiable.
        error_px: (B, 2) predicted minus true ``t_xy``, in pixels of the keyframe image.
        t_xy: (B, 2) predicted ``t_xy``, metres.
    """

    loss: Tensor
    error_px: Tensor
    t_xy: Tensor


def _as_scalar(value, ref: Tensor, name: str) -> Tensor:
    t = value.to(ref.dtype) if isinstance(value, Tensor) else torch.tensor(float(value), dtype=ref.dtype, device=ref.device)
    if t.dim() != 0:
        raise ShapeError(f"{name}: expected a float or a 0-d tensor, got shape {tuple(t.shape)}")
    return t


def kcc_shift_loss(pairs: KCCPairs, sigma, lam, temperature, cfg: KCCConfig | None = None) -> KCCLoss:
    """Train a KCC on each keyframe, correlate its frame and score the soft arg-max ``t_xy`` (NI-SLAM Eq. (11), (17), (18)).

    Differentiable in ``sigma``, ``lam`` and ``temperature`` (and in the images).

    Args:
        pairs: B keyframe/frame pairs.
        sigma: kernel width σ, a float or 0-d tensor (may require grad).
        lam: regulariser λ, a float or 0-d tensor.
        temperature: soft arg-max temperature, a float or 0-d tensor.
        cfg: PSR window (the other settings were used when the pairs were built).

    Returns:
        KCCLoss.
    """
    cfg = cfg or KCCConfig()
    ref = pairs.keyframe
    s, lm, T = (_as_scalar(v, ref, n) for v, n in ((sigma, "sigma"), (lam, "lam"), (temperature, "temperature")))
    filt = kcc_train(pairs.keyframe, s, lm)
    pred = kcc_predict(pairs.frame, filt, s, pairs.resolution, psr_window=cfg.psr_window, temperature=T)
    err = (pred.t_xy - pairs.t_xy) / pairs.resolution[:, None]
    return KCCLoss(err.square().sum(dim=1).mean(), err, pred.t_xy)


def kcc_pair_errors(pairs: KCCPairs, cfg: KCCConfig, sigma: float | None = None, lam: float | None = None) -> Tensor:
    """Errors of the shift a plain run measures: hard peak with ``cfg.subpixel`` refinement (or
    the soft arg-max where ``cfg.soft_argmax``), no gradients.

    Args:
        pairs: B pairs.
        cfg: correlator settings; ``sigma`` / ``lam`` override its σ and λ.
        sigma: kernel width, or None for ``cfg.sigma``.
        lam: regulariser, or None for ``cfg.lam``.

    Returns:
        (B, 2) predicted minus true ``t_xy``, metres.
    """
    s = cfg.sigma if sigma is None else float(sigma)
    lm = cfg.lam if lam is None else float(lam)
    if not (s > 0 and lm > 0 and math.isfinite(s) and math.isfinite(lm)):
        raise ConfigError(f"sigma, lam: expected positive numbers, got {s!r}, {lm!r}")
    with torch.no_grad():
        filt = kcc_train(pairs.keyframe, s, lm)
        pred = kcc_predict(
            pairs.frame, filt, s, pairs.resolution, cfg.subpixel, cfg.subpixel_smoothing, cfg.subpixel_iterations,
            cfg.psr_window, cfg.temperature if cfg.soft_argmax else None,
        )
    return pred.t_xy - pairs.t_xy
