"""ORB extraction: tensors in, OpenCV's own features out, batches, empty images, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.errors import ConfigError, DTypeError, ShapeError
from torchslam.features import DESCRIPTOR_BYTES, Features, ORBConfig, ORBScore, extract_orb, rgb_to_grey_u8


def _load_rgb(path: Path) -> torch.Tensor:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1).float() / 255.0


@pytest.fixture
def tum_frames(shared_data):
    names = sorted((shared_data / "tum_fr1_xyz" / "rgb").iterdir())
    return [_load_rgb(names[i]) for i in (0, 10)]


def test_defaults_are_the_gcslam_and_opencv_values():
    cfg = ORBConfig()
    assert (cfg.n_features, cfg.scale_factor, cfg.n_levels) == (2000, 1.2, 8)
    orb = cv2.ORB_create()
    assert cfg.fast_threshold == orb.getFastThreshold()
    assert cfg.edge_threshold == orb.getEdgeThreshold() and cfg.patch_size == orb.getPatchSize()
    assert cfg.score_type is ORBScore.HARRIS and orb.getScoreType() == cv2.ORB_HARRIS_SCORE


def test_grey_conversion_matches_opencv_within_one_level():
    gen = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 31, 47, generator=gen)
    grey = rgb_to_grey_u8(rgb)
    assert grey.shape == (2, 31, 47) and grey.dtype == torch.uint8
    for b in range(2):
        u8 = (rgb[b].permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)
        ref = cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY).astype(int)
        assert np.abs(grey[b].numpy().astype(int) - ref).max() <= 1


def test_features_equal_opencv_on_the_same_grey_image(tum_frames):
    rgb = tum_frames[0]
    f = extract_orb(rgb)
    assert isinstance(f, Features)
    grey = rgb_to_grey_u8(rgb[None])[0].numpy()
    kps, desc = cv2.ORB_create(nfeatures=2000, scaleFactor=1.2, nlevels=8).detectAndCompute(grey, None)
    assert len(f) == len(kps) and 1000 < len(f) <= 2000
    assert f.keypoints.dtype == torch.float32 and f.keypoints.shape == (len(f), 2)
    assert f.descriptors.dtype == torch.uint8 and f.descriptors.shape == (len(f), DESCRIPTOR_BYTES)
    assert np.array_equal(f.keypoints.numpy(), np.array([k.pt for k in kps], dtype=np.float32))
    assert np.array_equal(f.descriptors.numpy(), desc)
    assert np.array_equal(f.levels.numpy(), [k.octave for k in kps])
    assert np.allclose(f.responses.numpy(), [k.response for k in kps])
    h, w = rgb.shape[1:]
    assert (f.keypoints[:, 0] >= 0).all() and (f.keypoints[:, 0] < w).all()
    assert (f.keypoints[:, 1] >= 0).all() and (f.keypoints[:, 1] < h).all()
    assert f.levels.min() >= 0 and f.levels.max() < 8


def _assert_same_feature_set(got: Features, ref: Features, px_tol: float = 1e-3, resp_rtol: float = 1e-4) -> None:
    """The two hold the same keypoints in any order: each matched one-to-one to a keypoint of the
    same level within ``px_tol`` pixels, with the same response (to ``resp_rtol``) and descriptor."""
    assert len(got) == len(ref)
    if len(ref) == 0:
        return
    d = torch.cdist(got.keypoints.double(), ref.keypoints.double())  # (K, K) pixels
    d[got.levels[:, None] != ref.levels[None, :]] = float("inf")
    dist, j = d.min(dim=1)
    assert float(dist.max()) <= px_tol, float(dist.max())
    assert torch.equal(j.sort().values, torch.arange(len(ref)))  # one-to-one
    torch.testing.assert_close(got.responses, ref.responses[j], rtol=resp_rtol, atol=1e-9)
    assert torch.equal(got.descriptors, ref.descriptors[j])


def test_batch_equals_per_image_and_is_ragged(tum_frames):
    flat = torch.full_like(tum_frames[0], 0.5)
    batch = torch.stack([tum_frames[0], flat, tum_frames[1]])
    out = extract_orb(batch, ORBConfig(n_features=500))
    assert isinstance(out, list) and len(out) == 3
    assert len(out[1]) == 0  # a flat image has no corners: K = 0, not an error
    for got, img in zip(out, batch):
        _assert_same_feature_set(got, extract_orb(img, ORBConfig(n_features=500)))
    assert len(out[0]) > 400 and len(out[2]) > 400
    # the comparison is order-free: the same features in another order are the same set
    perm = torch.randperm(len(out[0]), generator=torch.Generator().manual_seed(0))
    _assert_same_feature_set(Features(*(getattr(out[0], f)[perm] for f in ("keypoints", "descriptors", "levels", "responses"))), out[0])


def test_grey_conversion_does_not_depend_on_the_batch():
    # ORB sees uint8 grey levels: one level off in a few pixels changes the keypoints, so an
    # image must convert to the same levels alone and in any batch (odd sizes, float32 and 64).
    gen = torch.Generator().manual_seed(1)
    for dtype in (torch.float32, torch.float64):
        rgb = torch.rand(5, 3, 37, 53, generator=gen, dtype=dtype)
        grey = rgb_to_grey_u8(rgb)
        for b in range(5):
            assert torch.equal(rgb_to_grey_u8(rgb[b : b + 1])[0], grey[b])
        assert torch.equal(rgb_to_grey_u8(rgb[1:4]), grey[1:4])
        assert torch.equal(rgb_to_grey_u8(rgb[:, :, 1:, 2:]), grey[:, 1:, 2:])  # a strided view


def test_empty_image_gives_empty_tensors():
    f = extract_orb(torch.zeros(3, 64, 80))
    assert len(f) == 0
    assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 32) and f.descriptors.dtype == torch.uint8
    assert f.levels.shape == (0,) and f.responses.shape == (0,)


def test_fewer_features_and_fast_threshold_are_honoured(tum_frames):
    few = extract_orb(tum_frames[0], ORBConfig(n_features=100))
    assert 0 < len(few) <= 100
    strict = extract_orb(tum_frames[0], ORBConfig(n_features=5000, fast_threshold=60, min_fast_threshold=60))
    loose = extract_orb(tum_frames[0], ORBConfig(n_features=5000, fast_threshold=10, min_fast_threshold=10))
    assert len(strict) < len(loose)


def test_low_contrast_image_is_detected_again_at_the_lower_threshold(tum_frames):
    """Oracle: OpenCV's ORB at ``min_fast_threshold`` on the same grey image."""
    dull = tum_frames[0] * 0.12 + 0.4  # a tenth of the contrast: FAST at 20 keeps few corners
    grey = rgb_to_grey_u8(dull[None])[0].numpy()
    at20 = cv2.ORB_create(nfeatures=2000, fastThreshold=20).detect(grey, None)
    kps, desc = cv2.ORB_create(nfeatures=2000, fastThreshold=7).detectAndCompute(grey, None)
    assert len(at20) < 200 < len(kps)  # below a tenth of the 2000 features asked for
    f = extract_orb(dull)
    assert np.array_equal(f.keypoints.numpy(), np.array([k.pt for k in kps], dtype=np.float32))
    assert np.array_equal(f.descriptors.numpy(), desc)
    # Off: the lower threshold not below fast_threshold, or no share low enough to ask for it.
    assert len(extract_orb(dull, ORBConfig(min_fast_threshold=20))) == len(at20)
    assert len(extract_orb(dull, ORBConfig(retry_below=len(at20) / 2000))) == len(at20)
    assert len(extract_orb(dull, ORBConfig(retry_below=(len(at20) + 1) / 2000))) == len(kps)


def test_bad_input_raises():
    with pytest.raises(ShapeError, match=r"rgb: expected \(3, H, W\) or \(B, 3, H, W\), got \(1, 8, 8\)"):
        extract_orb(torch.zeros(1, 8, 8))
    with pytest.raises(ShapeError, match="rgb"):
        extract_orb(np.zeros((3, 8, 8)))
    with pytest.raises(DTypeError, match="rgb: expected float32 or float64"):
        extract_orb(torch.zeros(3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ConfigError, match="scale_factor"):
        ORBConfig(scale_factor=1.0)
    with pytest.raises(ConfigError, match="wta_k"):
        ORBConfig(wta_k=3)
    assert ORBConfig(score_type="fast").score_type is ORBScore.FAST
    with pytest.raises(ConfigError, match=r"score_type: 'sobel' is not one of \['harris', 'fast'\]"):
        ORBConfig(score_type="sobel")
    with pytest.raises(ConfigError, match="n_features"):
        ORBConfig(n_features=0)
    with pytest.raises(ConfigError, match="min_fast_threshold"):
        ORBConfig(min_fast_threshold=-1)
    with pytest.raises(ConfigError, match="retry_below"):
        ORBConfig(retry_below=1.5)


def test_config_from_yaml_mapping():
    cfg = config_from_dict(ORBConfig, {"n_features": 1000, "score_type": "fast"})
    assert cfg.n_features == 1000 and cfg.score_type is ORBScore.FAST
    with pytest.raises(ConfigError, match="levels"):
        config_from_dict(ORBConfig, {"levels": 4})
