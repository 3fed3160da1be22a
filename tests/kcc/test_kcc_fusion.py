import math

import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, DTypeError, ShapeError
from torchslam.kcc import (
    KCCConfig,
    KeyframeMap,
    OrthoImages,
    choose_resolution,
    depth_translation,
    fuse_keyframe,
    keyframe_map,
    orthographic_project,
    rgbd_to_points,
    shift_image,
)

from tests._helpers import seeded


@pytest.fixture
def kf(tum_rgbd):
    """Orthographic images (1, 360, 480) float64 of a real frame, with their natural holes."""
    rgb, depth, intr = tum_rgbd
    pts, grey, valid = rgbd_to_points(rgb.double(), depth.double(), intr.double())
    r = choose_resolution(pts, valid)
    return orthographic_project(pts, grey, valid, None, r)


def _moved(o: OrthoImages, s, dz=0.0, dgrey=0.0) -> OrthoImages:
    """The frame whose content is ``o`` moved by integer ``s`` (B, 2), depth + dz, grey + dgrey."""
    back = -torch.as_tensor(s)
    valid = shift_image(o.valid, back, False)
    grey = torch.where(valid, shift_image(o.grey, back, 0.0) + dgrey, torch.zeros_like(o.grey))
    dz = torch.as_tensor(dz, dtype=o.depth.dtype).reshape(-1, 1, 1)
    depth = torch.where(valid, shift_image(o.depth, back, 0.0) + dz, torch.zeros_like(o.depth))
    return OrthoImages(grey, depth, valid, o.resolution, o.center)


def _expand(o: OrthoImages, B: int) -> OrthoImages:
    return OrthoImages(
        o.grey.expand(B, -1, -1),
        o.depth.expand(B, -1, -1),
        o.valid.expand(B, -1, -1),
        o.resolution.expand(B),
        o.center.expand(B, -1),
    )


def test_shift_image_equals_loop_and_is_not_circular():
    img = torch.arange(2 * 5 * 6, dtype=torch.float64).reshape(2, 5, 6)
    s = torch.tensor([[2, -1], [-3, 4]])
    out = shift_image(img, s, fill=-1.0)
    ref = np.full((2, 5, 6), -1.0)
    for b in range(2):
        for i in range(5):
            for j in range(6):
                ii, jj = i + int(s[b, 1]), j + int(s[b, 0])
                if 0 <= ii < 5 and 0 <= jj < 6:
                    ref[b, i, j] = img[b, ii, jj]
    np.testing.assert_array_equal(out.numpy(), ref)
    mask = shift_image(torch.ones(2, 5, 6, dtype=torch.bool), s, False)
    assert mask.dtype == torch.bool and torch.equal(mask, torch.from_numpy(ref >= 0))
    # Float shifts are rounded to the nearest pixel.
    assert torch.equal(shift_image(img, s.double() + 0.2, -1.0), out)


def test_shift_image_single_item_slice_path_equals_loop_for_every_shift():
    # B = 1 takes a slice copy instead of the batched gather: check it against the definition
    # out[i, j] = img[i + s_y, j + s_x] for every shift, including ones past the border.
    img = torch.rand(1, 5, 6, generator=seeded(3), dtype=torch.float64)
    for sx in range(-7, 8):
        for sy in range(-6, 7):
            s = torch.tensor([[sx, sy]])
            ref = np.full((1, 5, 6), -1.0)
            for i in range(5):
                for j in range(6):
                    if 0 <= i + sy < 5 and 0 <= j + sx < 6:
                        ref[0, i, j] = img[0, i + sy, j + sx]
            np.testing.assert_array_equal(shift_image(img, s, fill=-1.0).numpy(), ref)
            mask = shift_image(img > 0.5, s, False)
            assert mask.dtype == torch.bool
            np.testing.assert_array_equal(mask.numpy(), (ref > 0.5))


def test_depth_translation_planted_with_noise_and_a_moving_object(kf):
    cfg = KCCConfig()
    s = torch.tensor([[9, -5]])
    frame = _moved(kf, s, dz=0.037)
    # A "moving object": a block whose grey and depth changed; it must not count.
    obj = torch.zeros_like(frame.valid)
    obj[:, 100:160, 200:280] = True
    grey = torch.where(obj & frame.valid, frame.grey + 0.4, frame.grey)
    noise = 0.004 * torch.randn(frame.depth.shape, generator=seeded(1), dtype=torch.float64)
    depth = torch.where(frame.valid, frame.depth + noise, frame.depth)
    depth = torch.where(obj & frame.valid, depth - 0.3, depth)
    noisy = OrthoImages(grey, depth, frame.valid, frame.resolution, frame.center)
    out = depth_translation(noisy, kf, s, cfg.T_c, cfg.T_d)
    both = kf.valid & shift_image(frame.valid, s, False)
    moved_obj = shift_image(obj, s, False)
    assert out.ok.all() and out.count[0] == (both & ~moved_obj).sum()
    assert torch.equal(out.matched[0], (both & ~moved_obj)[0])
    assert abs(out.t_z.item() - 0.037) < 1e-4
    assert out.variance.item() == pytest.approx(0.004**2, rel=0.05)
    # Noise-free: exact mean, zero variance.
    clean = depth_translation(frame, kf, s)
    assert clean.t_z.item() == pytest.approx(0.037, abs=1e-12) and clean.variance.item() < 1e-20


def test_depth_translation_beyond_threshold_reports_empty_or_uses_median(kf):
    s = torch.tensor([[0, 3]])
    frame = _moved(kf, s, dz=0.25)  # |t_z| > T_d = 0.1: the paper's test matches nothing
    paper = depth_translation(frame, kf, s)
    assert not paper.ok.any() and paper.count.item() == 0
    assert paper.t_z.item() == 0.0 and math.isinf(paper.variance.item())
    assert not torch.isnan(paper.t_z).any() and not paper.matched.any()
    robust = depth_translation(frame, kf, s, median_center=True)
    assert robust.ok.all() and robust.t_z.item() == pytest.approx(0.25, abs=1e-12)
    # Nothing valid at all: empty in both modes, never NaN.
    empty = OrthoImages(frame.grey, frame.depth, torch.zeros_like(frame.valid), frame.resolution, frame.center)
    for median in (False, True):
        e = depth_translation(empty, kf, s, median_center=median)
        assert e.count.item() == 0 and e.t_z.item() == 0.0 and math.isinf(e.variance.item())


def test_depth_translation_median_ignores_one_sided_outliers(kf):
    """Differences that pass the depth test but are one-sided (depth edges) bias the mean, not the median."""
    s = torch.tensor([[2, -3]])
    frame = _moved(kf, s, dz=0.02)
    # A quarter of the pixels 6 cm too far: inside T_d = 10 cm of the true 2 cm, so they match.
    edge = torch.rand(frame.depth.shape, generator=seeded(3), dtype=torch.float64) < 0.25
    depth = torch.where(frame.valid & edge, frame.depth + 0.06, frame.depth)
    noisy = OrthoImages(frame.grey, depth, frame.valid, frame.resolution, frame.center)
    mean = depth_translation(noisy, kf, s, median_center=True)
    median = depth_translation(noisy, kf, s, median_center=True, statistic="median")
    assert torch.equal(mean.matched, median.matched) and torch.equal(mean.count, median.count)
    assert mean.t_z.item() == pytest.approx(0.02 + 0.06 * 0.25, abs=0.003)  # biased by ~1.5 cm
    assert median.t_z.item() == pytest.approx(0.02, abs=1e-12)
    # Batched (nanmedian path) equals per item (kthvalue path).
    two = OrthoImages(*(torch.cat([getattr(noisy, f)] * 2) for f in ("grey", "depth", "valid", "resolution")),
                      torch.cat([noisy.center] * 2))
    both = depth_translation(two, _expand(kf, 2), s.expand(2, 2), median_center=True, statistic="median")
    assert torch.equal(both.t_z, median.t_z.expand(2))
    with pytest.raises(ConfigError, match="statistic"):
        depth_translation(noisy, kf, s, statistic="mode")
    with pytest.raises(ConfigError, match="depth_statistic"):
        KCCConfig(depth_statistic="trimmed")


def test_depth_translation_batched_equals_per_item(kf):
    s = torch.tensor([[4, 1], [-7, 2], [0, 0]])
    dz = torch.tensor([0.01, -0.05, 0.0], dtype=torch.float64)
    frames = [_moved(kf, s[i : i + 1], dz=dz[i : i + 1]) for i in range(3)]
    fields = ("grey", "depth", "valid", "resolution", "center")
    batch = OrthoImages(*(torch.cat([getattr(f, n) for f in frames]) for n in fields))
    out = depth_translation(batch, _expand(kf, 3), s)
    for i in range(3):
        one = depth_translation(frames[i], kf, s[i : i + 1])
        assert torch.equal(one.matched[0], out.matched[i]) and one.count[0] == out.count[i]
        torch.testing.assert_close(one.t_z[0], out.t_z[i])
    torch.testing.assert_close(out.t_z, dz, atol=1e-12, rtol=0)


def test_fusion_leaves_an_aligned_identical_keyframe_unchanged(kf):
    m = keyframe_map(kf)
    m2 = KeyframeMap(m.grey, m.depth, m.weight * 3)  # after a few fusions
    dz = depth_translation(kf, m2, torch.zeros(1, 2, dtype=torch.long))
    assert dz.t_z.item() == 0.0
    out = fuse_keyframe(m2, kf, torch.zeros(1, 2, dtype=torch.long), dz.t_z, dz.matched, torch.tensor([500.0]))
    assert torch.equal(out.grey, m.grey) and torch.equal(out.depth, m.depth)  # bit-identical, no blur
    assert torch.equal(out.weight, m.weight * 4)


def test_fusion_fills_holes_and_skips_unmatched_pixels(kf):
    cfg = KCCConfig()
    s = torch.tensor([[6, -4]])
    # Keyframe with an extra hole block; the frame (the full view moved by s, depth + 2 cm) sees it.
    hole = torch.zeros_like(kf.valid)
    hole[:, 150:200, 220:300] = True
    kv = kf.valid & ~hole
    keyframe = OrthoImages(kf.grey * kv, kf.depth * kv, kv, kf.resolution, kf.center)
    frame = _moved(kf, s, dz=0.02)
    # A moving object in the frame, outside the hole block.
    obj = torch.zeros_like(kf.valid)
    obj[:, 40:80, 40:90] = True
    obj_frame = shift_image(obj, -s, False)
    grey = torch.where(obj_frame, frame.grey + 0.5, frame.grey)
    frame = OrthoImages(grey, frame.depth, frame.valid, frame.resolution, frame.center)
    dz = depth_translation(frame, keyframe, s, cfg.T_c, cfg.T_d)
    fused = fuse_keyframe(keyframe_map(keyframe), frame, s, dz.t_z, dz.matched, torch.tensor([cfg.T_M + 1]), cfg.T_M)
    seen = shift_image(frame.valid, s, False)
    filled = hole & kf.valid & seen
    assert filled.sum() > 1000
    torch.testing.assert_close(fused.grey[filled], kf.grey[filled], atol=1e-12, rtol=0)
    torch.testing.assert_close(fused.depth[filled], kf.depth[filled], atol=1e-12, rtol=0)
    assert (fused.weight[filled] == 1).all() and fused.valid[filled].all()
    # The object's pixels did not match: keyframe values and weights untouched there.
    bad = obj & kv & seen
    assert bad.sum() > 500
    assert torch.equal(fused.grey[bad], keyframe.grey[bad]) and (fused.weight[bad] == 1).all()
    # Everywhere else the content agreed: values unchanged up to round-off, weight 2.
    rest = kv & seen & ~obj
    torch.testing.assert_close(fused.grey[rest], keyframe.grey[rest], atol=1e-12, rtol=0)
    torch.testing.assert_close(fused.depth[rest], keyframe.depth[rest], atol=1e-12, rtol=0)
    assert (fused.weight[rest] == 2).all()


def test_fusion_is_the_weighted_moving_average_and_gated_by_psr():
    gen = seeded(3)
    B, H, W = 2, 12, 14
    zg = torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    zd = 1 + torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    wz = torch.randint(0, 4, (B, H, W), generator=gen).double()
    xg = zg + 0.05 * torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    xd = zd + 0.03 + 0.02 * torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    xv = torch.rand(B, H, W, generator=gen) > 0.2
    km = KeyframeMap(zg * (wz > 0), zd * (wz > 0), wz)
    ones, zeros = torch.ones(B, dtype=torch.float64), torch.zeros(B, 2, dtype=torch.float64)
    frame = OrthoImages(xg * xv, xd * xv, xv, ones, zeros)
    zero = torch.zeros(B, 2, dtype=torch.long)
    dz = depth_translation(frame, km, zero)
    out = fuse_keyframe(km, frame, zero, dz.t_z, dz.matched, torch.tensor([150.0, 80.0]), 100.0)
    # Item 0 (PSR 150 > 100): Eq. (23) with e -> 0 and w^x from Eq. (24).
    wx = (xv & (dz.matched | (wz == 0))).double()
    s = wz + wx
    num_g = wz * km.grey + wx * xg
    num_d = wz * km.depth + wx * (xd - dz.t_z[:, None, None])
    exp_g = torch.where(s > 0, num_g / s.clamp_min(1), 0.0)
    exp_d = torch.where(s > 0, num_d / s.clamp_min(1), 0.0)
    torch.testing.assert_close(out.grey[0], exp_g[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(out.depth[0], exp_d[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(out.weight[0], s[0])
    # Item 1 (PSR 80 <= 100): untouched.
    assert torch.equal(out.grey[1], km.grey[1]) and torch.equal(out.weight[1], km.weight[1])
    # Inputs are not modified.
    assert torch.equal(km.weight, wz)


def test_fusion_and_depth_translation_reject_bad_input(kf):
    m = keyframe_map(kf)
    s = torch.zeros(1, 2, dtype=torch.long)
    with pytest.raises(ShapeError, match="shift"):
        depth_translation(kf, kf, torch.zeros(2, 2))
    with pytest.raises(ShapeError, match="keyframe.grey"):
        depth_translation(kf, OrthoImages(kf.grey[:, :10], kf.depth, kf.valid, kf.resolution, kf.center), s)
    with pytest.raises(DTypeError, match="matched"):
        fuse_keyframe(m, kf, s, torch.zeros(1), kf.valid.float(), torch.ones(1))
    with pytest.raises(ShapeError, match="psr"):
        fuse_keyframe(m, kf, s, torch.zeros(1), kf.valid, torch.ones(2))
    with pytest.raises(ShapeError, match="image"):
        shift_image(torch.zeros(4, 4), torch.zeros(1, 2))


def test_centred_medians_equal_two_masked_medians():
    """The single-compaction medians of ``median_center`` + ``statistic="median"`` equal the two-step ones (ties, empty sets)."""
    from torchslam.kcc.fusion import _centred_medians, _masked_lower_median

    gen = seeded(5)
    for trial in range(6):
        diff = (torch.randn(1, 20, 30, generator=gen, dtype=torch.float64) * 0.1).round(decimals=2)  # many ties
        if trial == 1:
            diff[0, :, :15] += 0.5  # a second mode far from the median: matched is a strict subset
        cand = torch.rand(1, 20, 30, generator=gen) > (0.3 if trial != 2 else 1.0)  # trial 2: no candidate
        T_d = 0.05 if trial != 3 else 1e-9  # trial 3: only exact ties with the centre match
        center, t_z, matched = _centred_medians(diff, cand, T_d)
        ref_center = _masked_lower_median(diff, cand)
        ref_matched = cand & ((diff - ref_center[:, None, None]).abs() < T_d)
        assert torch.equal(center, ref_center) and torch.equal(matched, ref_matched)
        assert torch.equal(t_z, _masked_lower_median(diff, ref_matched))
