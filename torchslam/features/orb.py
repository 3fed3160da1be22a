"""ORB keypoints and binary descriptors from colour tensors, extracted with OpenCV.

GC-SLAM's sparse front-end (FastGO paper §IV-A1) and NI-SLAM's relocalisation (NI-SLAM §9.1) both
describe a keyframe by its ORB features. OpenCV does the detection and the 256-bit rBRIEF
descriptors; torchslam only converts tensors to a grey ``uint8`` image and the result back to
tensors on the input's device.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch
from torch import Tensor

from ..errors import AT_LEAST_1, NON_NEGATIVE, ConfigError, Limit, ShapeError, check_float, check_limits, parse_choice

__all__ = ["ORBConfig", "ORBScore", "Features", "extract_orb", "rgb_to_grey_u8", "DESCRIPTOR_BYTES"]

logger = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32
"""Bytes of one ORB descriptor (256 bits)."""

# ITU-R BT.601 luma weights, the ones OpenCV's RGB->grey conversion uses.
_LUMA_RGB = (0.299, 0.587, 0.114)


class ORBScore(enum.Enum):
    """Keypoint ranking used to keep the best ``n_features`` corners."""

    HARRIS = "harris"
    FAST = "fast"


@dataclass(frozen=True)
class ORBConfig:
    """ORB detector and descriptor settings.

    Defaults follow the GC-SLAM authors' released code (2000 features, scale factor 1.2, 8 pyramid
    levels); the remaining fields keep OpenCV's defaults (FAST threshold 20, 31-pixel patch and
    border, Harris ranking, 2-point BRIEF tests).

    Attributes:
        n_features: most keypoints kept per image.
        scale_factor: pyramid decimation ratio (> 1).
        n_levels: pyramid levels.
        edge_threshold: border in pixels where no keypoint is detected.
        first_level: pyramid level of the source image.
        wta_k: points per BRIEF comparison; only 2 gives the 256-bit Hamming descriptor used here.
        score_type: keypoint ranking.
        patch_size: BRIEF patch size in pixels.
        fast_threshold: FAST intensity threshold in grey levels (0..255).
        min_fast_threshold: the lower FAST threshold of a low-contrast image (strong motion blur,
            dim light): an image with fewer than ``retry_below * n_features`` keypoints at
            ``fast_threshold`` is detected again at this one, and that result is kept (ORB-SLAM's
            extractor lowers its threshold from 20 to 7 the same way, per image cell). At or above
            ``fast_threshold`` it is off.
        retry_below: the share of ``n_features`` below which an image is detected again: a tenth,
            too few corners to register a frame by (docs/results/gcslam.md, "Blurred frames detected again");
            an image with more keeps its corners at ``fast_threshold``.
    """

    n_features: int = 2000
    scale_factor: float = 1.2
    n_levels: int = 8
    edge_threshold: int = 31
    first_level: int = 0
    wta_k: int = 2
    score_type: ORBScore = ORBScore.HARRIS
    patch_size: int = 31
    fast_threshold: int = 20
    min_fast_threshold: int = 7
    retry_below: float = 0.1

    LIMITS: ClassVar[dict[str, Limit]] = {
        "n_features": AT_LEAST_1, "scale_factor": Limit(gt=1), "n_levels": AT_LEAST_1, "edge_threshold": NON_NEGATIVE,
        "first_level": NON_NEGATIVE, "wta_k": Limit(ge=2, le=2), "patch_size": Limit(ge=2), "fast_threshold": Limit(ge=0, le=255),
        "min_fast_threshold": Limit(ge=0, le=255), "retry_below": Limit(ge=0, le=1),
    }

    def __post_init__(self) -> None:
        if self.wta_k != 2:
            # WTA_K > 2 changes the descriptor's meaning so that Hamming distance no longer applies.
            raise ConfigError(f"wta_k: only 2 (Hamming-comparable descriptors) is supported, got {self.wta_k}")
        check_limits(self)
        if not self.first_level < self.n_levels:
            raise ConfigError(f"first_level: must be in [0, n_levels), got {self.first_level}")
        object.__setattr__(self, "score_type", parse_choice(ORBScore, self.score_type, "score_type"))


@dataclass(frozen=True)
class Features:
    """ORB features of one image.

    Attributes:
        keypoints: (K, 2) float32 pixel coordinates ``(u, v)`` in the full-resolution image, with
            pixel centres at integers (OpenCV's convention).
        descriptors: (K, 32) uint8 256-bit rBRIEF descriptors.
        levels: (K,) int64 pyramid level (octave) each keypoint was found at.
        responses: (K,) float32 corner score used for ranking.
    """

    keypoints: Tensor
    descriptors: Tensor
    levels: Tensor
    responses: Tensor

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def to(self, device: torch.device | str) -> "Features":
        """Return the same features on ``device``."""
        return Features(
            self.keypoints.to(device), self.descriptors.to(device), self.levels.to(device), self.responses.to(device)
        )


def rgb_to_grey_u8(rgb: Tensor) -> Tensor:
    """Convert colour in [0, 1] to 8-bit grey with the BT.601 luma weights.

    Args:
        rgb: (B, 3, H, W) float32/float64 colour in [0, 1] (RGB channel order).

    Returns:
        (B, H, W) uint8 grey levels, ``round(255 * (0.299 R + 0.587 G + 0.114 B))`` clamped to [0, 255];
        an image's grey levels do not depend on the batch it comes in.
    """
    # Element-wise products and sums in a fixed order, not a contraction (einsum/matmul): BLAS
    # kernels pick their blocking by shape and CPU, so a contraction's rounding (and with it a
    # grey level, and ORB's keypoints) could depend on the batch an image comes in.
    wr, wg, wb = _LUMA_RGB
    grey = rgb[:, 0] * wr + rgb[:, 1] * wg + rgb[:, 2] * wb
    return (grey * 255.0).round_().clamp_(0, 255).to(torch.uint8)


def _make_orb(cfg: ORBConfig, fast_threshold: int | None = None):
    score = cv2.ORB_HARRIS_SCORE if cfg.score_type is ORBScore.HARRIS else cv2.ORB_FAST_SCORE
    return cv2.ORB_create(
        nfeatures=cfg.n_features,
        scaleFactor=cfg.scale_factor,
        nlevels=cfg.n_levels,
        edgeThreshold=cfg.edge_threshold,
        firstLevel=cfg.first_level,
        WTA_K=cfg.wta_k,
        scoreType=score,
        patchSize=cfg.patch_size,
        fastThreshold=cfg.fast_threshold if fast_threshold is None else fast_threshold,
    )


def _features_from_cv(keypoints, descriptors, device: torch.device) -> Features:
    k = 0 if descriptors is None else len(keypoints)
    if k == 0:
        # OpenCV returns None descriptors for an image without corners: give empty tensors instead.
        return Features(
            keypoints=torch.zeros(0, 2, dtype=torch.float32, device=device),
            descriptors=torch.zeros(0, DESCRIPTOR_BYTES, dtype=torch.uint8, device=device),
            levels=torch.zeros(0, dtype=torch.int64, device=device),
            responses=torch.zeros(0, dtype=torch.float32, device=device),
        )
    # OpenCV's converter for the positions (one C++ call); generators for the rest (no lists).
    pts = np.asarray(cv2.KeyPoint_convert(keypoints), dtype=np.float32).reshape(k, 2)
    levels = np.fromiter((kp.octave for kp in keypoints), dtype=np.int64, count=k)
    resp = np.fromiter((kp.response for kp in keypoints), dtype=np.float32, count=k)
    return Features(
        keypoints=torch.from_numpy(pts).to(device),
        descriptors=torch.from_numpy(np.ascontiguousarray(descriptors, dtype=np.uint8)).to(device),
        levels=torch.from_numpy(levels).to(device),
        responses=torch.from_numpy(resp).to(device),
    )


def extract_orb(rgb: Tensor, cfg: ORBConfig | None = None) -> Features | list[Features]:
    """Detect ORB keypoints and compute their descriptors.

    The colour image is converted to grey in torch (BT.601 luma, :func:`rgb_to_grey_u8`) and
    handed to OpenCV's ORB. OpenCV processes one image at a time, so a batch is a loop over its
    images; the feature count differs per image, so a batch gives a list (ragged). An image
    without corners gives ``K = 0`` features, not an error.

    Args:
        rgb: (3, H, W) or (B, 3, H, W) float32/float64 colour in [0, 1].
        cfg: detector settings; None uses ``ORBConfig()``.

    Returns:
        ``Features`` for a (3, H, W) input, or a list of B ``Features`` for a batch, on
        ``rgb.device``.

    Raises:
        ShapeError: ``rgb`` is not (3, H, W) or (B, 3, H, W).
        DTypeError: ``rgb`` is not float32/float64.
    """
    if not isinstance(rgb, Tensor) or rgb.dim() not in (3, 4) or rgb.shape[-3] != 3:
        got = tuple(rgb.shape) if isinstance(rgb, Tensor) else type(rgb).__name__
        raise ShapeError(f"rgb: expected (3, H, W) or (B, 3, H, W), got {got}")
    check_float(rgb, "rgb")
    cfg = ORBConfig() if cfg is None else cfg
    single = rgb.dim() == 3
    batch = rgb.unsqueeze(0) if single else rgb
    grey = rgb_to_grey_u8(batch.detach()).cpu().numpy()  # (B, H, W) uint8
    orb, low = _make_orb(cfg), None
    retry = cfg.min_fast_threshold < cfg.fast_threshold
    out = []
    for img in grey:
        img = np.ascontiguousarray(img)
        kps, desc = orb.detectAndCompute(img, None)
        if retry and len(kps) < cfg.retry_below * cfg.n_features:
            # Low contrast (blur, dim light): FAST at the lower threshold finds the corners again.
            low = _make_orb(cfg, cfg.min_fast_threshold) if low is None else low
            kps, desc = low.detectAndCompute(img, None)
        out.append(_features_from_cv(kps, desc, rgb.device))
    logger.debug("extract_orb: %s keypoints", [len(f) for f in out])
    return out[0] if single else out
