"""``KCCConfig.masked_kernel``: kernel distances summed over the pixels both images hold."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.kcc import (
    KCCConfig, choose_resolution, frame_taper, keyframe_filter, keyframe_map, orthographic_project, rgbd_to_points, track_step,
)
from torchslam.kcc.correlator import (
    KernelCorrelator, kcc_features_masked, kcc_predict, kcc_train, kernel_correlation, masked_kernel_map, standardize_masked,
)
from torchslam.systems.nislam import NISlamConfig

from tests._helpers import run_nislam


def _direct(x_t, z_t, w_x, w_z, sigma):
    """Float64 reference: every circular shift by rolling, the distance summed pixel by pixel."""
    B, C, H, W = x_t.shape
    out = torch.empty(B, H, W, dtype=torch.float64)
    for a in range(H):  # the oracle loops over shifts on purpose
        for b in range(W):
            z_s, w_s = torch.roll(z_t, (a, b), (-2, -1)), torch.roll(w_z, (a, b), (-2, -1))
            d2 = (w_x * w_s * (x_t - z_s).square()).sum(dim=(1, 2, 3))
            out[:, a, b] = torch.exp(-d2 / (sigma**2 * C * H * W))
    return out


def test_masked_kernel_equals_direct_sums_over_the_overlap():
    g = torch.Generator().manual_seed(0)
    B, C, H, W = 2, 2, 6, 7
    x_t = torch.randn(B, C, H, W, generator=g, dtype=torch.float64)
    z_t = torch.randn(B, C, H, W, generator=g, dtype=torch.float64)
    # Soft frame weights (a taper) with holes, binary keyframe weights with holes.
    w_x = (torch.rand(B, 1, H, W, generator=g, dtype=torch.float64) > 0.3) * torch.rand(B, 1, H, W, generator=g, dtype=torch.float64)
    w_z = (torch.rand(B, 1, H, W, generator=g, dtype=torch.float64) > 0.3).double()
    got = masked_kernel_map(w_x * x_t, w_z * z_t, 0.7, w_x, w_z)
    torch.testing.assert_close(got, _direct(x_t, z_t, w_x, w_z, 0.7), rtol=0, atol=1e-13)


def test_full_weights_give_the_unmasked_kernel():
    g = torch.Generator().manual_seed(1)
    x, z = torch.randn(2, 2, 8, 10, generator=g, dtype=torch.float64), torch.randn(2, 2, 8, 10, generator=g, dtype=torch.float64)
    one = torch.ones(2, 1, 8, 10, dtype=torch.float64)
    torch.testing.assert_close(masked_kernel_map(x, z, 0.5, one, one), kernel_correlation(x, z, 0.5), rtol=0, atol=1e-13)


def test_gradients_through_the_masked_kernel():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(1, 2, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    z = torch.randn(1, 2, 5, 6, generator=g, dtype=torch.float64)
    sigma = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    w_x = torch.rand(1, 1, 5, 6, generator=g, dtype=torch.float64) + 0.1
    w_z = (torch.rand(1, 1, 5, 6, generator=g, dtype=torch.float64) > 0.2).double()
    assert torch.autograd.gradcheck(lambda x_, s_: masked_kernel_map(x_ * w_x, z * w_z, s_, w_x, w_z), (x, sigma))


def _smooth(x: torch.Tensor, s: int) -> torch.Tensor:
    k = torch.arange(-3 * s, 3 * s + 1, dtype=x.dtype)
    g = torch.exp(-k.square() / (2 * s * s))
    g = g / g.sum()
    C = x.shape[1]
    x = F.conv2d(F.pad(x, (3 * s, 3 * s, 0, 0), mode="circular"), g.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(F.pad(x, (0, 0, 3 * s, 3 * s), mode="circular"), g.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_holes_fixed_to_the_camera_no_longer_pull_the_shift_towards_zero(seed):
    # Planted: the frame is the keyframe's content moved by (-6, 4) px (circularly, so no
    # border); both images lose the same pixels (a band and a block fixed to the camera). The
    # unmasked kernel counts those holes as zeros that line up at no motion and falls short;
    # the masked kernel measures the shift.
    g = torch.Generator().manual_seed(seed)
    H, W = 96, 128
    content = _smooth(torch.randn(1, 2, H, W, generator=g, dtype=torch.float64), 2)
    frame = torch.roll(content, (4, -6), (-2, -1))
    m = torch.ones(1, 1, H, W, dtype=torch.float64)
    m[..., :, :30] = 0
    m[..., 70:, 60:90] = 0
    z, x = standardize_masked(content, m), standardize_masked(frame, m)
    truth = torch.tensor([-6.0, 4.0], dtype=torch.float64)
    plain = kcc_predict(x, kcc_train(z, 0.2, 0.1), 0.2).shift[0]
    masked = kcc_predict(x, kcc_train(z, 0.2, 0.1, mask=m), 0.2, mask=m).shift[0]
    assert (masked - truth).abs().max() < 0.02, masked
    assert (plain[0] - truth[0]).abs() > 0.04, plain  # the unmasked kernel's shortfall, for contrast
    assert (plain[0] - truth[0]) > 0  # short of -6, towards no motion


def test_filter_and_frame_must_agree_on_the_mask():
    z = torch.randn(1, 2, 8, 8, dtype=torch.float64)
    m = torch.ones(1, 1, 8, 8, dtype=torch.float64)
    with pytest.raises(ConfigError, match="trained with a mask"):
        kcc_predict(z, kcc_train(z, 0.2, 0.1, mask=m), 0.2)
    with pytest.raises(ConfigError, match="trained without a mask"):
        kcc_predict(z, kcc_train(z, 0.2, 0.1), 0.2, mask=m)


def test_channel_weights_hold_the_fill_mask_and_the_frames_taper():
    seq = generate_sequence(SyntheticConfig(frames=1, trajectory="handheld", seed=0, width=320, height=240))
    f = seq[0]
    pts, grey, valid = rgbd_to_points(f.rgb[None], f.depth[None], seq.camera.as_tensor(torch.float32)[None])
    size = (120, 160)
    r = choose_resolution(pts, valid, size, 0.8, 25)
    ortho = orthographic_project(pts, grey, valid, None, r, size)
    cfg = KCCConfig(ortho_height=size[0], ortho_width=size[1], frame_taper=12, masked_kernel=True)
    corr = KernelCorrelator(cfg)
    _, fill = kcc_features_masked(ortho.grey, ortho.depth, ortho.valid, cfg.channel_norm, cfg.fill_holes)
    z, w_kf = corr.channels(ortho, mask=True)
    x, w_fr = corr.channels(ortho, frame=True, mask=True)
    assert torch.equal(w_kf, fill)
    torch.testing.assert_close(w_fr, fill * frame_taper(*size, 12))
    assert torch.equal(z * (w_kf == 0), torch.zeros_like(z))  # 0 off the weights
    assert torch.equal(corr.channels(ortho, frame=True), x)  # the channels themselves unchanged


def test_track_step_measures_a_planted_translation_with_the_masked_kernel():
    seq = generate_sequence(SyntheticConfig(frames=1, trajectory="handheld", seed=3, width=320, height=240))
    f = seq[0]
    pts, grey, valid = rgbd_to_points(f.rgb[None], f.depth[None], seq.camera.as_tensor(torch.float32)[None])
    size = (180, 240)
    cfg = dataclasses.replace(NISlamConfig().kcc, ortho_height=size[0], ortho_width=size[1], frame_taper=12, masked_kernel=True)
    r = choose_resolution(pts, valid, size, cfg.coverage, cfg.sample_step)
    km = keyframe_map(orthographic_project(pts, grey, valid, None, r, size))
    filt = keyframe_filter(km, cfg)
    assert filt.mask_terms is not None
    truth = torch.tensor([0.04, -0.025, 0.0])
    res = track_step(pts + truth, grey, valid, torch.eye(3)[None], km, filt, r, cfg)
    assert (res.t_content[0, :2] - truth[:2]).abs().max() < 0.25 * float(r), (res.t_content, r)


def test_nislam_runs_with_the_masked_kernel():
    assert NISlamConfig().kcc.masked_kernel  # NI-SLAM's default
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="translate", seed=1, width=320, height=240))
    masked, a = run_nislam(seq, attitude="imu", loop={"enabled": False}, kcc={"masked_kernel": True})
    plain, _ = run_nislam(seq, attitude="imu", loop={"enabled": False}, kcc={"masked_kernel": False})
    assert a.stats["rmse"] < 0.01, a.stats
    assert not torch.allclose(masked.output.T_wc, plain.output.T_wc, rtol=0, atol=1e-6)  # the setting reached the matches
