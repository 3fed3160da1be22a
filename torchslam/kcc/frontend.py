"""The KCC tracking step of NI-SLAM: frames matched against their keyframes, batched and pure.

Two recipes live here and nowhere else:

- the keyframe recipe (``keyframe_filter``): a keyframe's fused orthographic map becomes KCC
  channels (``kcc_channels``: ``kcc_features`` windowed by ``apply_window``) and a trained filter (``kcc_train``);
- the tracking step (``track_step``): a frame's cloud is projected in the keyframe's attitude at
  the keyframe's resolution, matched against the filter (``kcc_predict``) and its depth shift
  taken from the well-matched pixels (``depth_translation``), NI-SLAM Eq. (4)-(21).

σ, λ and the soft arg-max temperature reach the kernel through one ``KernelCorrelator``; both
functions accept a ``KCCConfig`` instead, which builds that module from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .correlator import FeatureKind, KCCConfig, KCCFilter, KernelCorrelator, kcc_features
from .features import load_feature_net
from .fusion import KeyframeMap, depth_translation
from .ortho import OrthoImages, orthographic_project
from .window import apply_window, taper_frame

__all__ = ["TrackResult", "TrackSummary", "correlator_for", "kcc_channels", "keyframe_filter", "summarize", "track_step"]


@dataclass(frozen=True)
class TrackResult:
    """One batched tracking step against the current keyframes.

    Attributes:
        t_content: (B, 3) scene-content translation ``(t_xy, t_z)`` in the keyframe attitude
            frame, metres (the image centre included); the frame's camera sits at
            ``-t_content`` from the keyframe's.
        variance: (B, 3) variances of ``t_content``, m^2.
        psr: (B,) peak-to-sidelobe ratio.
        matched_fraction: (B,) fraction of the frame's valid orthographic pixels well matched.
        frame: the frame's orthographic images (around the step's ``center``).
        index: (B, 2) integer content shift of ``frame`` against the keyframe, used for depth
            and fusion.
        depth_ok: (B,) bool, some pixels were well matched (t_z is meaningful).
        matched: (B, H, W) bool well-matched set.
        response: (B, H, W) correlation output.
    """

    t_content: Tensor
    variance: Tensor
    psr: Tensor
    matched_fraction: Tensor
    frame: OrthoImages
    index: Tensor
    depth_ok: Tensor
    matched: Tensor
    response: Tensor


@dataclass(frozen=True)
class TrackSummary:
    """The host-side numbers of one item of a ``TrackResult``: what decisions and poses need.

    Read back from the device for a whole batch in one transfer (``summarize``); the values are
    the result's own, in float64 (exact: the float32 ones widen without rounding).

    Attributes:
        t_content: (3,) float64 scene-content translation, metres (``TrackResult.t_content``).
        variance: (3,) float64 its variances, m^2.
        psr: peak-to-sidelobe ratio.
        matched_fraction: fraction of the frame's valid pixels well matched.
        depth_ok: some pixels were well matched.
        index: (1, 2) int64 integer content shift ``(s_x, s_y)`` (``TrackResult.index``), on the host.
    """

    t_content: Tensor
    variance: Tensor
    psr: float
    matched_fraction: float
    depth_ok: bool
    index: Tensor


def summarize(res: TrackResult) -> list[TrackSummary]:
    """Read a batch's host-side numbers back from the device in one transfer.

    Returns:
        One ``TrackSummary`` per item, in order.
    """
    f64 = torch.float64
    packed = torch.cat(
        [res.t_content.to(f64), res.variance.to(f64), res.psr.to(f64)[:, None], res.matched_fraction.to(f64)[:, None],
         res.depth_ok.to(f64)[:, None], res.index.to(f64)],
        dim=1,
    ).cpu()  # (B, 11): the one synchronisation
    index = packed[:, 9:11].to(torch.int64)
    rows = packed[:, 6:9].tolist()
    return [
        TrackSummary(packed[b, 0:3], packed[b, 3:6], rows[b][0], rows[b][1], rows[b][2] > 0, index[b : b + 1])
        for b in range(packed.shape[0])
    ]


def correlator_for(cfg: KCCConfig | KernelCorrelator) -> KernelCorrelator:
    """The correlator of ``cfg``: itself if it is one, else a fixed (non-learnable) one built from it.

    Its values are held in float64 so that they reach float32 and float64 inputs rounded once,
    as a plain float would. With ``cfg.features == "learned"`` it holds the network read from
    ``cfg.features_weights`` (empty: the weights that ship with torchslam, ``PACKAGED_WEIGHTS``).
    """
    if isinstance(cfg, KernelCorrelator):
        return cfg
    features = load_feature_net(cfg.features_weights or None) if cfg.features is FeatureKind.LEARNED else None
    return KernelCorrelator(cfg, dtype=torch.float64, features=features)


def kcc_channels(images: OrthoImages | KeyframeMap, cfg: KCCConfig | KernelCorrelator, frame: bool = False) -> Tensor:
    """(B, C, H, W) KCC input of orthographic images (``KernelCorrelator.channels``).

    The one recipe for keyframe and frame alike: the hand-crafted ``kcc_features`` (C = 2,
    ``cfg.channel_norm``, ``cfg.fill_holes``) or the learned channels (``cfg.features``), then
    ``cfg.window``, and for a frame's images (``frame``) ``cfg.frame_taper``. Given settings
    rather than a correlator, learned channels use the weights ``cfg.features_weights`` names
    (or the packaged ones).
    """
    if isinstance(cfg, KCCConfig) and cfg.features is FeatureKind.HANDCRAFTED:
        z = apply_window(kcc_features(images.grey, images.depth, images.valid, cfg.channel_norm, cfg.fill_holes), cfg.window)
        return taper_frame(z, cfg.frame_taper) if frame else z
    return correlator_for(cfg).channels(images, frame=frame)


def keyframe_filter(kf_map: KeyframeMap | OrthoImages, correlator: KCCConfig | KernelCorrelator) -> KCCFilter:
    """Train the correlator on keyframes: their channels (``KernelCorrelator.channels``), then ``kcc_train`` (Eq. (9)-(11)).

    Args:
        kf_map: the keyframes' (fused) orthographic maps, (B, H, W) ``grey``, ``depth``, ``valid``.
        correlator: the correlator (or its settings).

    Returns:
        KCCFilter, B keyframes.
    """
    corr = correlator_for(correlator)
    z, w = corr.channels(kf_map, mask=True) if corr.cfg.masked_kernel else (corr.channels(kf_map), None)
    return corr.fit(z, w)


def track_step(
    points: Tensor,
    grey: Tensor,
    valid: Tensor,
    R_kf_frame: Tensor,
    kf_map: KeyframeMap,
    kf_filter: KCCFilter,
    resolution: Tensor,
    cfg: KCCConfig | KernelCorrelator,
    center: Tensor | None = None,
) -> TrackResult:
    """Match frames against their keyframes (NI-SLAM Eq. (4)–(21)), batched.

    Args:
        points: (B, N, 3) camera-frame points, metres.
        grey: (B, N) grey values in [0, 1].
        valid: (B, N) bool validity.
        R_kf_frame: (B, 3, 3) rotation from the frame's camera into the keyframe attitude
            (``R_wk^T R_wi``).
        kf_map: the keyframes' fused orthographic maps, (B, H, W) fields.
        kf_filter: the correlators trained on those maps (``keyframe_filter``).
        resolution: (B,) keyframe resolutions ``r_k``, metres per pixel.
        cfg: the correlator, or its settings.
        center: (B, 2) where the frame's orthographic image is centred, as a content translation
            ``(t_x, t_y)`` in metres (``orthographic_project``'s ``center``), rounded to whole
            pixels of ``resolution`` (the points then fall into the same pixels as on the
            frame's axis, shifted); ``None``: on the frame's own optical axis (the paper).
            Centred on a predicted translation, the frame's image window lies over the
            keyframe's and the correlation measures only the prediction's error: the image
            borders, which do not move with the content, pull the peak towards zero shift by
            4–13 % of the shift (``scripts/bench_window.py``). ``t_content`` includes the
            centre; ``index``, ``matched`` and ``frame`` are those of the centred image (what
            fusion and the depth test need).

    Returns:
        TrackResult.
    """
    corr = correlator_for(cfg)
    k = corr.cfg
    size = (k.ortho_height, k.ortho_width)
    if center is not None:
        # Whole pixels: the frame's points then fall into the same pixels as on its own axis,
        # shifted, so the sub-pixel measurement does not depend on the prediction.
        r = resolution.to(points.device, points.dtype)[:, None]
        center = torch.round(center.to(points.device, points.dtype) / r) * r
    fr = orthographic_project(points, grey, valid, R_kf_frame.to(points.device, points.dtype), resolution, size, center)
    # Tapered (``frame_taper``); the keyframe's filter is not. Weights only for the masked kernel.
    x, w = corr.channels(fr, frame=True, mask=True) if k.masked_kernel else (corr.channels(fr, frame=True), None)
    pred = corr(x, kf_filter, resolution, mask=w)
    dz = depth_translation(fr, kf_map, pred.index, k.T_c, k.T_d, k.depth_median_center, k.depth_statistic)
    n_valid = fr.valid.flatten(1).sum(-1).clamp_min(1)
    t_xy = pred.t_xy if center is None else pred.t_xy + center
    t = torch.cat([t_xy, dz.t_z[:, None]], dim=-1)
    var = torch.stack([pred.variance, pred.variance, dz.variance], dim=-1)
    return TrackResult(
        t_content=t,
        variance=var,
        psr=pred.psr,
        matched_fraction=dz.count.to(points.dtype) / n_valid,
        frame=fr,
        index=pred.index,
        depth_ok=dz.ok,
        matched=dz.matched,
        response=pred.response,
    )
