"""NI-SLAM front-end core: orthographic re-projection, kernel cross-correlator, PSR, depth translation, map fusion.

Pure, batched functions over ``(B, ...)`` tensors plus the thin ``KernelCorrelator`` module.
The pieces compose as (see each module for equations and conventions)::

    points, grey, valid = rgbd_to_points(rgb, depth, intrinsics)
    r_k = choose_resolution(points_k, valid_k)                            # at a new keyframe
    kf = orthographic_project(points_k, grey_k, valid_k, None, r_k)
    filt = kcc_train(kcc_features(kf.grey, kf.depth, kf.valid), sigma, lam)
    fr = orthographic_project(points_i, grey_i, valid_i, R_ki, r_k)       # R_ki = R_wk^T R_wi
    pred = kcc_predict(kcc_features(fr.grey, fr.depth, fr.valid), filt, sigma, r_k)
    dz = depth_translation(fr, kf, pred.index)
    # scene content moved by t = (pred.t_xy, dz.t_z): the frame camera is at -t from the keyframe

``features`` holds the learned alternative to ``kcc_features`` (``KCCConfig.features``).
``frontend`` holds that recipe as two calls taking a config (or a ``KernelCorrelator``):
``keyframe_filter(kf_map, cfg)`` for the training lines and ``track_step(...)`` for the rest.
"""

from .correlator import (
    ChannelNorm,
    FeatureKind,
    KCCConfig,
    KCCFilter,
    KCCPrediction,
    KernelCorrelator,
    Subpixel,
    find_peak,
    kcc_features,
    kcc_features_masked,
    kcc_predict,
    kcc_response,
    kcc_train,
    kernel_correlation,
    masked_kernel_map,
    spectral_energy,
    standardize_masked,
)
from .features import PACKAGED_WEIGHTS, KCCFeatureNet, load_feature_net
from .frontend import TrackResult, TrackSummary, correlator_for, kcc_channels, keyframe_filter, summarize, track_step
from .fusion import DepthStatistic, DepthTranslation, KeyframeMap, depth_translation, fuse_keyframe, keyframe_map, shift_image
from .ortho import (
    OrthoImages,
    choose_resolution,
    grey_from_rgb,
    orthographic_project,
    rgbd_to_points,
    sample_grey,
    sample_grey_rotated,
    sample_grey_warped,
)
from .peak import Peak, peak_to_sidelobe, shift_variance, soft_argmax
from .refine import MapRefineConfig, MapRefinement, refine_against_map
from .window import Window, apply_window, frame_taper, kcc_window

__all__ = [
    "ChannelNorm",
    "DepthStatistic",
    "FeatureKind",
    "DepthTranslation",
    "KCCConfig",
    "KCCFeatureNet",
    "KCCFilter",
    "KCCPrediction",
    "KernelCorrelator",
    "KeyframeMap",
    "MapRefineConfig",
    "MapRefinement",
    "OrthoImages",
    "PACKAGED_WEIGHTS",
    "Peak",
    "Subpixel",
    "TrackResult",
    "TrackSummary",
    "Window",
    "apply_window",
    "choose_resolution",
    "correlator_for",
    "depth_translation",
    "find_peak",
    "frame_taper",
    "fuse_keyframe",
    "grey_from_rgb",
    "kcc_channels",
    "kcc_features",
    "kcc_features_masked",
    "kcc_predict",
    "kcc_response",
    "kcc_train",
    "kcc_window",
    "kernel_correlation",
    "masked_kernel_map",
    "keyframe_filter",
    "keyframe_map",
    "load_feature_net",
    "orthographic_project",
    "peak_to_sidelobe",
    "refine_against_map",
    "rgbd_to_points",
    "sample_grey",
    "sample_grey_rotated",
    "sample_grey_warped",
    "shift_image",
    "shift_variance",
    "soft_argmax",
    "spectral_energy",
    "standardize_masked",
    "summarize",
    "track_step",
]
