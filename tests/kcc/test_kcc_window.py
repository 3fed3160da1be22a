"""The KCC window (``torchslam.kcc.window``): its values, where it applies, and what it does to a static border."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, ShapeError
from torchslam.kcc import KCCConfig, Window, apply_window, kcc_features, kcc_predict, kcc_train, kcc_window

from .conftest import load_tum_frame


def test_hann_window_matches_its_formula_and_is_separable():
    w = kcc_window("hann", 6, 9, torch.float64)
    ref = np.outer(np.sin(np.pi * (np.arange(6) + 0.5) / 6) ** 2, np.sin(np.pi * (np.arange(9) + 0.5) / 9) ** 2)
    np.testing.assert_allclose(w.numpy(), ref, rtol=0, atol=1e-15)
    assert (w > 0).all() and (w <= 1).all()
    torch.testing.assert_close(w, w.flip(0).flip(1), rtol=0, atol=1e-15)  # symmetric about the centre
    assert torch.linalg.matrix_rank(w) == 1


def test_window_is_cached_per_size_dtype_and_device():
    a = kcc_window(Window.HANN, 12, 16, torch.float32)
    assert kcc_window("hann", 12, 16, torch.float32) is a
    assert kcc_window("hann", 12, 16, torch.float64).dtype == torch.float64
    assert kcc_window("none", 12, 16) is None


def test_apply_window_none_is_the_identity_and_hann_multiplies_every_channel():
    x = torch.randn(2, 2, 8, 10, dtype=torch.float64)
    assert apply_window(x, "none") is x
    torch.testing.assert_close(apply_window(x, "hann"), x * kcc_window("hann", 8, 10, torch.float64), rtol=0, atol=0)
    with pytest.raises(ShapeError, match="x"):
        apply_window(x[0], "hann")


def test_config_parses_the_window_and_names_it_when_wrong():
    assert KCCConfig(window="hann").window is Window.HANN
    assert KCCConfig().window is Window.NONE  # the paper's default
    with pytest.raises(ConfigError, match="window"):
        KCCConfig(window="hamming")


def test_hann_window_weakens_the_pull_of_a_static_border_towards_zero_shift(shared_data):
    # Two crops of the same real image, 7 px right and 5 px down of each other: the content moves,
    # the crop border does not (not a circular shift). Standardised channels as in tracking.
    rgb, _ = load_tum_frame(str(shared_data), 0)
    grey = torch.from_numpy(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0)
    H, W, sx, sy = 160, 200, 7, 5
    z = grey[100 : 100 + H, 150 : 150 + W]
    x = grey[100 - sy : 100 - sy + H, 150 - sx : 150 - sx + W]  # x[p] = z[p - s]
    ones = torch.ones(1, H, W, dtype=torch.bool)

    def chans(img):
        return kcc_features(img[None], img[None], ones, "standardize", 1)

    errors = {}
    for kind in ("none", "hann"):
        zc, xc = apply_window(chans(z), kind), apply_window(chans(x), kind)
        pred = kcc_predict(xc, kcc_train(zc, 0.2, 0.1), 0.2)
        errors[kind] = (pred.shift[0] - torch.tensor([sx, sy], dtype=torch.float64)).norm().item()
    assert errors["hann"] < 0.25, errors
    assert errors["hann"] < errors["none"], errors
    assert math.isfinite(errors["none"])


def test_track_step_windows_keyframe_and_frame_when_configured(tum_rgbd):
    from torchslam.kcc import choose_resolution, keyframe_filter, keyframe_map, orthographic_project, rgbd_to_points, track_step

    rgb, depth, intr = tum_rgbd
    p, g, v = rgbd_to_points(rgb, depth, intr[None])
    shifted = p + torch.tensor([0.01, -0.005, 0.0])  # content moved 1 cm right, 5 mm up
    out = {}
    for kind in ("none", "hann"):
        cfg = KCCConfig(window=kind, ortho_height=240, ortho_width=320)
        r = choose_resolution(p, v, (240, 320), cfg.coverage, cfg.sample_step)
        km = keyframe_map(orthographic_project(p, g, v, None, r, (240, 320)))
        out[kind] = track_step(shifted, g, v, torch.eye(3)[None], km, keyframe_filter(km, cfg), r, cfg)
    assert not torch.allclose(out["none"].response, out["hann"].response)
    for res in out.values():  # either way the planted centimetre is found to half a millimetre
        torch.testing.assert_close(res.t_content[0, :2].double(), torch.tensor([0.01, -0.005], dtype=torch.float64), atol=5e-4, rtol=0)
