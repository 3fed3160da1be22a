"""Dense registration: analytic Jacobians vs autograd, planted poses, PairStats vs brute force, real pairs."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import kornia
import pytest
import torch
import torch.nn.functional as F

from torchslam.data import SyntheticConfig, TUMSequence, generate_sequence
from torchslam.data.synthetic import kinect_depth_noise
from torchslam.errors import ConfigError, DTypeError, ShapeError
from torchslam.fastgo import PairStats, pair_cost
from torchslam.geometry import (
    PinholeCamera,
    se3_act,
    se3_exp,
    se3_inverse,
    se3_log,
    undistorted_rays,
)
from torchslam.registration import dense as dense_module
from torchslam.registration.dense import (
    DenseConfig,
    DenseFrame,
    _linearize,
    _reduce_depth,
    _select_pixels,
    _subsample,
    _warp,
    dense_correspondences,
    dense_images,
    prepare_dense_frame,
    register_dense,
    register_dense_frames,
)

F64 = torch.float64
FR1_DISTORTION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
# float32 frames prepared alone and in a batch: equal to round-off, not bit for bit
_BATCH_TOL = dict(rtol=1e-5, atol=1e-6)


def pose_error(T_est: torch.Tensor, T_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(translation metres, rotation degrees) of ``inv(T_ref) @ T_est``."""
    e = se3_log(se3_inverse(T_ref) @ T_est)
    return e[..., :3].norm(dim=-1), torch.rad2deg(e[..., 3:].norm(dim=-1))


@pytest.fixture(scope="module")
def synthetic():
    """Noise-free 320x240 frames 0, 4, 8 of the hand-held trajectory and the planted ``T_0j``."""
    seq = generate_sequence(SyntheticConfig(frames=9, width=320, height=240, depth_noise=False, trajectory="handheld", batch_size=9))
    rgb, depth = seq.render([0, 4, 8])
    T = seq.groundtruth.T_wc
    return seq.camera, rgb, depth, se3_inverse(T[0]) @ T[[4, 8]]


@functools.lru_cache(maxsize=1)
def _fr1_frames(root: str):
    seq = TUMSequence(Path(root) / "tum_fr1_xyz")
    return seq.camera, [seq[k] for k in (0, 5, 10)]


@pytest.fixture
def fr1(shared_data):
    return _fr1_frames(str(shared_data))


# ------------------------------------------------------------------ configuration and building blocks


@pytest.mark.parametrize(
    "key, value",
    [("levels", 0), ("iterations", (10, 10)), ("robust", "cauchy"), ("min_depth", -1.0), ("max_depth", 0.05),
     ("correspondence_threshold", 0.0), ("geometric_weight", -1.0), ("max_correspondences", 0), ("tol", float("nan")),
     ("finest_tol", -1e-3)],
)
def test_config_rejects_bad_values(key, value):
    with pytest.raises(ConfigError, match=key):
        DenseConfig(**{key: value})


def test_robust_error_lists_valid_kernels():
    with pytest.raises(ConfigError, match=r"robust: 'tukey' is not one of \['student_t', 'huber'\]"):
        DenseConfig(robust="tukey")


def test_valid_aware_depth_reduction_matches_loop():
    g = torch.Generator().manual_seed(0)
    depth = 1.0 + torch.rand(2, 1, 8, 12, generator=g, dtype=F64) * 0.06
    depth[torch.rand(depth.shape, generator=g) < 0.3] = 0.0
    depth[0, 0, 0:2, 0:2] = torch.tensor([[1.0, 3.0], [0.0, 1.0]], dtype=F64)  # two surfaces: invalid
    tol = 0.04
    out = _reduce_depth(depth, 2, tol)
    ref = torch.zeros(2, 1, 4, 6, dtype=F64)
    for b in range(2):
        for r in range(4):
            for c in range(6):
                block = depth[b, 0, 2 * r : 2 * r + 2, 2 * c : 2 * c + 2].reshape(-1)
                v = block[block > 0]
                if len(v) and v.max() - v.min() <= tol * v.min():
                    ref[b, 0, r, c] = v.mean()
    assert out[0, 0, 0, 0] == 0
    assert torch.equal(out > 0, ref > 0) and (ref > 0).sum() > 5 and (ref == 0).sum() > 5
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)


def test_working_images_match_kornia_grey_and_a_masked_block_loop():
    g = torch.Generator().manual_seed(4)
    H, W = 48, 64
    cam = PinholeCamera(60.0, 60.0, 31.5, 23.5, W, H)
    rgb = torch.rand(2, 3, H, W, generator=g, dtype=F64)
    depth = 1.0 + 0.02 * torch.rand(2, 1, H, W, generator=g, dtype=F64)
    bad = torch.rand(depth.shape, generator=g)
    depth[bad < 0.05] = float("nan")
    depth[(bad >= 0.05) & (bad < 0.1)] = float("inf")
    depth[(bad >= 0.1) & (bad < 0.15)] = 0.05  # below min_depth
    depth[(bad >= 0.15) & (bad < 0.2)] = 0.0
    cfg = DenseConfig(width=32, height=24, levels=1, iterations=(1,))
    lv = prepare_dense_frame(rgb, depth, cam, cfg).levels[0]
    torch.testing.assert_close(lv.grey, F.avg_pool2d(kornia.color.rgb_to_grayscale(rgb), 2), rtol=0, atol=1e-12)
    good = torch.isfinite(depth) & (depth >= cfg.min_depth) & (depth <= cfg.max_depth)
    ref = _reduce_depth(torch.where(good, depth, torch.zeros_like(depth)), 2, cfg.depth_merge_tolerance)
    torch.testing.assert_close(lv.depth, ref, rtol=0, atol=1e-12)
    assert (lv.depth > 0).float().mean() > 0.3 and (lv.depth == 0).any()


def test_subsample_keeps_an_even_deterministic_subset():
    g = torch.Generator().manual_seed(1)
    cand = torch.rand(3, 1000, generator=g) < torch.tensor([[0.9], [0.3], [0.05]])
    keep = _subsample(cand, 100)
    counts = cand.sum(-1)
    assert keep.sum(-1).tolist() == torch.clamp(counts, max=100).tolist()
    assert not (keep & ~cand).any()
    assert torch.equal(keep[2], cand[2])  # fewer candidates than the cap: all kept
    # Evenly spread: the kept ranks among the candidates step by about c / k.
    ranks = (torch.cumsum(cand[0].long(), 0) - 1)[keep[0]]
    gaps = ranks.diff()
    assert gaps.min() >= int(counts[0]) // 100 and gaps.max() <= int(counts[0]) // 100 + 1
    assert torch.equal(keep, _subsample(cand, 100))


@pytest.mark.parametrize("step", [1, 2, 3])
def test_pixel_selection_matches_loop(synthetic, step):
    cam, rgb, depth, _ = synthetic
    holes = depth[:2].clone()
    holes[0, :, :, :100] = 0.0  # the two frames keep different numbers of pixels
    lv = prepare_dense_frame(rgb[:2], holes, cam, DenseConfig()).levels[0]
    px = _select_pixels(lv, step)
    h, w = lv.grey.shape[-2:]
    M = px.valid.shape[1]
    for b in range(2):
        want = [r * w + c for r in range(h) for c in range(w) if (r + c) % step == 0 and lv.valid[b, r * w + c]]
        n = len(want)
        assert int(px.valid[b].sum()) == n and px.valid[b, :n].all()
        assert torch.equal(px.points[b, :n], lv.points[b, want])
        assert torch.equal(px.grey[b, :n], lv.grey[b].reshape(-1)[want])
        one = _select_pixels(lv._map(lambda x: x[b : b + 1]), step)  # the single-frame path
        assert one.valid.shape == (1, n) and one.valid.all()
        assert torch.equal(one.points[0], px.points[b, :n]) and torch.equal(one.grey[0], px.grey[b, :n])
    assert M == max(int(px.valid[b].sum()) for b in range(2))
    # No valid depth at all: one invalid placeholder pixel, never an empty list.
    empty = prepare_dense_frame(rgb[:1], depth[:1] * 0, cam, DenseConfig()).levels[0]
    assert _select_pixels(empty, step).valid.shape == (1, 1) and not _select_pixels(empty, step).valid.any()


def test_reference_built_once_and_kept_by_index_expand_cat(synthetic):
    cam, rgb, depth, _ = synthetic
    cfg = DenseConfig()
    a, b = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg), prepare_dense_frame(rgb[1:2], depth[1:2], cam, cfg)
    both = prepare_dense_frame(rgb[:2], depth[:2], cam, cfg)
    assert all("reference" not in lv.__dict__ for lv in a.levels)  # a current frame never needs it
    ref_a, ref_b = a.levels[0].reference, b.levels[0].reference
    assert a.levels[0].reference is ref_a  # kept
    assert a.expand(3).levels[0].reference.data_ptr() == ref_a.data_ptr()  # a view, not rebuilt
    cat = DenseFrame.cat([a, b])
    # frames prepared alone and as a batch agree to round-off (convolutions may block by batch size)
    assert "reference" in cat.levels[0].__dict__
    torch.testing.assert_close(cat.levels[0].reference, both.levels[0].reference, **_BATCH_TOL)
    torch.testing.assert_close(both[1].levels[0].reference, ref_b, **_BATCH_TOL)


# ------------------------------------------------------------------ Jacobian


def _affine_frames():
    """float64 frame i with affine grey and depth (bilinear sampling and Sobel are exact on it)."""
    H, W = 30, 40
    cam = PinholeCamera(35.0, 36.0, 19.3, 14.6, W, H)
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    rgb_i = (0.3 + 0.01 * u - 0.007 * v).expand(1, 3, H, W).clone()
    depth_i = (2.0 + 0.004 * u + 0.003 * v)[None, None]
    g = torch.Generator().manual_seed(2)
    rgb_j = torch.rand(1, 3, H, W, generator=g, dtype=F64)
    depth_j = 2.0 + 0.1 * torch.rand(1, 1, H, W, generator=g, dtype=F64)
    cfg = DenseConfig(width=W, height=H, levels=1, iterations=(1,))
    return prepare_dense_frame(rgb_i, depth_i, cam, cfg), prepare_dense_frame(rgb_j, depth_j, cam, cfg)


@pytest.mark.parametrize("twist", [[0.05, -0.03, 0.02, 0.02, -0.01, 0.03], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
def test_analytic_jacobian_matches_autograd_and_finite_differences(twist):
    fi, fj = _affine_frames()
    li, lj = fi.levels[0], fj.levels[0]
    T0 = se3_exp(torch.tensor([twist], dtype=F64))
    wp, J_I, J_Z = _linearize(li, lj, T0, 0.1)
    assert wp.m_Z.sum() > 500

    def residuals(xi):
        w = _warp(li, lj, se3_exp(xi)[None] @ T0, 0.1)
        return torch.cat([w.r_I, w.r_Z], dim=-1)[0]

    N = J_I.shape[1]
    # Reverse mode through grid_sample, one vector-Jacobian product per residual (batched).
    J_auto = torch.autograd.functional.jacobian(residuals, torch.zeros(6, dtype=F64), vectorize=True)
    torch.testing.assert_close(J_I[0][wp.m_I[0]], J_auto[:N][wp.m_I[0]], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(J_Z[0][wp.m_Z[0]], J_auto[N:][wp.m_Z[0]], rtol=1e-9, atol=1e-12)
    # Central differences, twist component by component (the Lie update, not just the chain rule).
    h = 1e-6
    for k in range(6):
        e = torch.zeros(6, dtype=F64)
        e[k] = h
        fd = (residuals(e) - residuals(-e)) / (2 * h)
        # Compare where the residual stays valid on both sides (the masks are not differentiable).
        wp_p = _warp(li, lj, se3_exp(e)[None] @ T0, 0.1)
        wp_m = _warp(li, lj, se3_exp(-e)[None] @ T0, 0.1)
        keep = torch.cat([wp.m_I[0] & wp_p.m_I[0] & wp_m.m_I[0], wp.m_Z[0] & wp_p.m_Z[0] & wp_m.m_Z[0]])
        assert keep.sum() > 1000
        torch.testing.assert_close(fd[keep], torch.cat([J_I[0, :, k], J_Z[0, :, k]])[keep], rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------ lens distortion


def test_undistortion_recovers_the_pinhole_image(synthetic):
    cam, rgb, depth, _ = synthetic
    H, W = cam.height, cam.width
    cam_d = dataclasses.replace(cam, distortion=FR1_DISTORTION)
    # Distort the ideal image: pixel (u, v) of the lens image shows the ideal ray undistorted_rays gives.
    rays = undistorted_rays(cam_d, F64)
    u = cam.fx * rays[:, 0] + cam.cx
    v = cam.fy * rays[:, 1] + cam.cy
    grid = torch.stack([u * 2 / (W - 1) - 1, v * 2 / (H - 1) - 1], -1).reshape(1, H, W, 2).float()
    rgb_d = F.grid_sample(rgb[:1], grid, mode="bilinear", align_corners=True)
    depth_d = F.grid_sample(depth[:1], grid, mode="nearest", align_corners=True)
    cfg = DenseConfig(width=W, height=H, levels=1, iterations=(1,))
    ideal = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg).levels[0]
    fixed = prepare_dense_frame(rgb_d, depth_d, cam_d, cfg).levels[0]
    ignored = prepare_dense_frame(rgb_d, depth_d, dataclasses.replace(cam, distortion=None), cfg).levels[0]
    assert fixed.camera == ideal.camera  # the prepared frame is an ideal pinhole
    m = (fixed.reference[:, dense_module._IOK] > 0) & (ideal.depth[:, 0] > 0)
    m[..., :8, :] = False
    m[..., -8:, :] = False
    assert m.float().mean() > 0.7
    err_fixed = (fixed.grey - ideal.grey)[:, 0][m].abs().mean()
    err_ignored = (ignored.grey - ideal.grey)[:, 0][m].abs().mean()
    assert err_fixed < 0.01 and err_ignored > 4 * err_fixed
    both = m & (fixed.depth[:, 0] > 0)
    rel = ((fixed.depth - ideal.depth)[:, 0][both] / ideal.depth[:, 0][both]).abs()
    assert rel.median() < 1e-3


@pytest.mark.parametrize("distortion", [None, FR1_DISTORTION])
def test_working_images_rebuild_the_prepared_pyramid(synthetic, distortion):
    # What GC-SLAM's optimiser keeps of a keyframe (dense_images, or a prepared frame's images())
    # gives back the same pyramid as preparing the frame: every level, the reference channels too.
    cam, rgb, depth, _ = synthetic
    cam = dataclasses.replace(cam, distortion=distortion)
    cfg = DenseConfig(width=160, height=120)
    full = prepare_dense_frame(rgb[:2], depth[:2], cam, cfg)
    images = dense_images(rgb[:2], depth[:2], cam, cfg)
    assert (images.inside is None) == (distortion is None) and len(images) == 2
    assert images.grey.shape == (2, 1, 120, 160)
    for rebuilt in (images.pyramid(), full.images().pyramid()):
        assert len(rebuilt.levels) == len(full.levels) and rebuilt.camera == full.camera
        for a, b in zip(rebuilt.levels, full.levels):
            assert a.camera == b.camera
            for name in ("grey", "depth", "inside", "points", "valid", "reference"):
                assert torch.equal(getattr(a, name), getattr(b, name)), name
    with pytest.raises(ShapeError, match="rgb"):
        dense_images(rgb[:2, :2], depth[:2], cam, cfg)


# ------------------------------------------------------------------ planted poses


@pytest.mark.parametrize("robust", ["student_t", "huber"])
def test_recovers_planted_pose_on_synthetic_frames(synthetic, robust):
    cam, rgb, depth, T_gt = synthetic
    res = register_dense(rgb[[0, 0]], depth[[0, 0]], rgb[1:], depth[1:], cam, cfg=DenseConfig(robust=robust))
    dt, dr = pose_error(res.T_ij, T_gt)
    # Planted motion: 3.4 cm / 2.3 deg and 6.5 cm / 3.8 deg; measured errors 0.18 / 0.22 mm and
    # 0.003 / 0.005 deg (student_t), 0.32 / 0.40 mm and 0.008 / 0.010 deg (huber); every pixel at
    # the finest level (finest_pixel_step=1) gives 0.17 / 0.22 mm.
    assert (dt < 5e-4).all() and (dr < 0.02).all(), (dt, dr)
    assert res.success.all()
    assert (res.num_correspondences == 50000).all()
    assert (res.residual_geometric < 0.01).all() and (res.residual_photometric < 0.05).all()
    assert (res.iterations > 0).all()
    assert res.T_ij.dtype == F64 and len(res) == 2


def test_finest_tol_ends_the_working_resolution_after_one_small_step(synthetic):
    cam, rgb, depth, T_gt = synthetic
    args = (rgb[[0, 0]], depth[[0, 0]], rgb[1:], depth[1:], cam)
    coarse = register_dense(*args, cfg=DenseConfig(iterations=(20, 15, 0)))
    one = register_dense(*args, cfg=DenseConfig(finest_tol=1e9))
    tight = register_dense(*args, cfg=DenseConfig(finest_tol=0.0))
    default = register_dense(*args)
    # A tolerance nothing falls short of: exactly one (kept) step at the working resolution after the coarse levels.
    assert torch.equal(one.iterations, coarse.iterations + 1)
    # A zero tolerance iterates on there (until a step raises the cost or the cap).
    assert (tight.iterations > one.iterations).all()
    assert (default.iterations <= tight.iterations).all()
    # The one step is what the accuracy needs: within 0.2 mm of iterating to the end.
    for res in (one, default):
        dt, dr = pose_error(res.T_ij, T_gt)
        dt_tight, _ = pose_error(tight.T_ij, T_gt)
        assert (dt < 5e-4).all() and (dr < 0.02).all(), (dt, dr)
        assert ((dt - dt_tight).abs() < 2e-4).all(), (dt, dt_tight)


def test_recovers_planted_pose_with_kinect_noise(synthetic):
    cam, rgb, depth, T_gt = synthetic
    g = torch.Generator().manual_seed(3)
    noisy = kinect_depth_noise(depth, k=0.0015, holes=0.05, generator=g)
    rgb_n = (rgb + 0.01 * torch.randn(rgb.shape, generator=g)).clamp(0, 1)
    res = register_dense(rgb_n[[0, 0]], noisy[[0, 0]], rgb_n[1:], noisy[1:], cam)
    dt, dr = pose_error(res.T_ij, T_gt)
    # Measured 0.3 mm / 0.007 deg (0->4) and 0.8 mm / 0.015 deg (0->8).
    assert (dt < 2e-3).all() and (dr < 0.1).all(), (dt, dr)
    assert res.success.all()


def test_pair_stats_equal_a_brute_force_build(synthetic):
    cam, rgb, depth, T_gt = synthetic
    cfg = DenseConfig(max_correspondences=20000)
    fi = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg)
    fj = prepare_dense_frame(rgb[1:], depth[1:], cam, cfg)
    res = register_dense_frames(fi.expand(2), fj, cfg=cfg)
    corr = dense_correspondences(fi.expand(2), fj, res.T_ij, cfg)
    assert corr.mask.sum(-1).tolist() == res.num_correspondences.tolist() == res.stats.count.tolist() == [20000, 20000]
    pi = [corr.points_i[b][corr.mask[b]] for b in range(2)]
    pj = [corr.points_j[b][corr.mask[b]] for b in range(2)]
    w = [1.0 / pj[b][:, 2] ** 2 for b in range(2)]
    ref = PairStats.from_correspondences(pi, pj, w)
    torch.testing.assert_close(res.stats.as_vector(), ref.as_vector(), rtol=1e-10, atol=1e-9)
    for b in range(2):
        q = se3_act(res.T_ij[b], pj[b])
        d = (pi[b] - q).norm(dim=-1)
        # points_i lies on the ray of T p_j within the selection threshold: |p_i - T p_j| < 0.02 |T p_j|.
        assert (d < cfg.correspondence_threshold * q.norm(dim=-1)).all()
        # FastGO's pair cost from the 28 numbers equals the per-correspondence sum (T_wi = I, T_wj = T_ij).
        T_wc = torch.stack([torch.eye(4, dtype=F64), res.T_ij[b]])
        brute = (w[b] * d**2).sum()
        cost = pair_cost(T_wc, torch.tensor([[0, 1]]), res.stats[b : b + 1])
        torch.testing.assert_close(cost[0], brute, rtol=1e-7, atol=1e-12)
        # The correspondences are true surface matches: small residual under the planted pose too.
        d_gt = (pi[b] - se3_act(T_gt[b], pj[b])).norm(dim=-1)
        assert (w[b] * d_gt**2).sum() / w[b].sum() < (2e-3) ** 2
        assert torch.quantile(d_gt, 0.9) < 2e-3


def test_batch_equals_per_pair_calls(synthetic):
    """The batched path (an accelerator's; on the CPU with the host paths off) equals one call
    per pair; on the CPU a batch runs pair by pair (``_register_each``) and equals those calls
    exactly, a pair without valid depth (failed) included."""
    cam, rgb, depth, _ = synthetic
    cfg = DenseConfig()
    fi = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg)
    fj = prepare_dense_frame(rgb[1:], depth[1:], cam, cfg)
    T_init = se3_exp(torch.tensor([[0.01, 0.0, 0.0, 0.0, 0.01, 0.0], [0.0] * 6], dtype=F64))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dense_module, "HOST_FAST_PATHS", False)
        batch = register_dense_frames(fi.expand(2), fj, T_init, cfg)
    empty = prepare_dense_frame(rgb[1:2], torch.zeros_like(depth[1:2]), cam, cfg)
    host = register_dense_frames(fi.expand(3), DenseFrame.cat([fj, empty]), torch.cat([T_init, T_init[:1]]), cfg)
    assert host.success.tolist() == [True, True, False] and int(host.num_correspondences[2]) == 0
    for b in range(3):
        one = register_dense_frames(fi, (fj[b] if b < 2 else empty), T_init[b % 2], cfg)
        for name in ("T_ij", "success", "num_correspondences", "iterations", "residual_photometric", "residual_geometric"):
            assert torch.equal(getattr(host, name)[b : b + 1], getattr(one, name)), name
        if b == 2:
            break
        assert torch.equal(host.stats[b : b + 1].as_vector(), one.stats.as_vector())
        # A batch pads each pair's valid-pixel list to the longest, so its float32 sums run over
        # more (zero) terms and round differently: equal to 1e-7 m, not bit for bit.
        torch.testing.assert_close(batch.T_ij[b : b + 1], one.T_ij, rtol=0, atol=1e-7)
        assert batch.iterations[b] == one.iterations[0]
        assert batch.num_correspondences[b] == one.num_correspondences[0]
        # The statistics follow the pose: sums over 50,000 correspondences, equal to 1e-5 relative.
        torch.testing.assert_close(batch.stats[b : b + 1].as_vector(), one.stats.as_vector(), rtol=1e-5, atol=1e-9)
        torch.testing.assert_close(batch.residual_photometric[b : b + 1], one.residual_photometric)


def test_dense_frame_index_expand_cat(synthetic):
    cam, rgb, depth, _ = synthetic
    cfg = DenseConfig()
    both = prepare_dense_frame(rgb[:2], depth[:2], cam, cfg)
    a, b = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg), prepare_dense_frame(rgb[1:2], depth[1:2], cam, cfg)
    cat = DenseFrame.cat([a, b])
    assert len(cat) == 2 and len(both[1]) == 1 and len(a.expand(3)) == 3
    for lc, lb in zip(cat.levels, both.levels):  # alone vs as a batch: equal to round-off
        torch.testing.assert_close(lc.reference, lb.reference, **_BATCH_TOL)
        torch.testing.assert_close(lc.points, lb.points, **_BATCH_TOL)
    torch.testing.assert_close(both[1].levels[2].grey, b.levels[2].grey, **_BATCH_TOL)
    assert [lv.grey.shape[-2:] for lv in a.levels] == [(240, 320), (120, 160), (60, 80)]
    with pytest.raises(ShapeError, match="expand"):
        both.expand(3)
    other = prepare_dense_frame(rgb[:1], depth[:1], cam, DenseConfig(levels=2, iterations=(5, 5)))
    with pytest.raises(ConfigError, match="fj"):
        register_dense_frames(a, other)
    with pytest.raises(ConfigError, match="frames\\[1\\]"):
        DenseFrame.cat([a, other])
    with pytest.raises(ShapeError, match="fj"):
        register_dense_frames(a, both)


# ------------------------------------------------------------------ failure and bad input


def test_missing_depth_fails_without_exception_or_nan(synthetic):
    cam, rgb, depth, _ = synthetic
    good = register_dense(rgb[:1], depth[:1], rgb[1:2], depth[1:2], cam)
    no_i = depth[:1].clone().zero_()
    rgb_i, rgb_j = rgb[[0, 0, 0]], rgb[[1, 1, 1]]
    depth_i = torch.cat([depth[:1], no_i, depth[:1]])
    depth_j = torch.cat([depth[1:2], depth[1:2], no_i])
    res = register_dense(rgb_i, depth_i, rgb_j, depth_j, cam)
    assert res.success.tolist() == [True, False, False]
    assert res.num_correspondences[1:].tolist() == [0, 0]
    for x in (res.T_ij, res.stats.as_vector(), res.residual_photometric, res.residual_geometric):
        assert not torch.isnan(x).any()
    assert torch.isfinite(res.T_ij).all()
    assert res.stats.n[1:].abs().max() == 0
    assert torch.isinf(res.residual_geometric[1:]).all()  # no valid geometric residual at all
    torch.testing.assert_close(res.T_ij[2], torch.eye(4, dtype=F64))  # nothing to align: the start pose
    # The failing pairs do not disturb the good one in the same batch.
    torch.testing.assert_close(res.T_ij[:1], good.T_ij, rtol=0, atol=1e-9)


def test_bad_input_names_the_argument(synthetic):
    cam, rgb, depth, _ = synthetic
    r, d = rgb[:1], depth[:1]
    with pytest.raises(ShapeError, match="rgb_i"):
        register_dense(r[:, :2], d, r, d, cam)
    with pytest.raises(ShapeError, match="depth_j"):
        register_dense(r, d, r, d[..., :-1], cam)
    with pytest.raises(ShapeError, match="rgb_j"):
        register_dense(r, d, rgb[:2], d, cam)
    with pytest.raises(ShapeError, match="T_init"):
        register_dense(r, d, r, d, cam, T_init=torch.eye(4, dtype=F64).expand(2, 4, 4))
    with pytest.raises(ShapeError, match="camera"):
        register_dense(r, d, r, d, cam.scaled(0.5))
    with pytest.raises(DTypeError, match="rgb_i"):
        register_dense((r * 255).to(torch.uint8), d, r, d, cam)
    with pytest.raises(ConfigError, match="cfg"):
        register_dense(r, d, r, d, cam, cfg={"levels": 2})
    with pytest.raises(ShapeError, match="rgb"):
        prepare_dense_frame(r[0], d, cam)
    with pytest.raises(ShapeError, match="too small"):
        prepare_dense_frame(r[..., :20, :20], d[..., :20, :20], dataclasses.replace(cam, width=20, height=20))


# ------------------------------------------------------------------ real data


def test_real_fr1_xyz_pairs_against_ground_truth(fr1):
    cam, (f0, f5, f10) = fr1
    res = register_dense(
        torch.stack([f0.rgb, f0.rgb]), torch.stack([f0.depth, f0.depth]),
        torch.stack([f5.rgb, f10.rgb]), torch.stack([f5.depth, f10.depth]), cam,
    )
    T_gt = torch.stack([se3_inverse(f0.T_wc) @ f.T_wc for f in (f5, f10)])
    dt, dr = pose_error(res.T_ij, T_gt)
    # Ground-truth motion 7.2 cm / 14.4 cm; measured errors 3.8 mm / 0.25 deg (0->5) and
    # 3.7 mm / 0.64 deg (0->10); the identity is off by the full motion.
    assert (dt < 0.012).all() and (dr < 1.2).all(), (dt, dr)
    dt0, _ = pose_error(torch.eye(4, dtype=F64), T_gt)
    assert (dt < dt0 / 5).all()
    assert res.success.all()
    assert ((res.num_correspondences > 30000) & (res.num_correspondences <= 50000)).all()


def test_host_update_matches_the_device_path():
    """The CPU NumPy Gauss-Newton update equals the torch one to round-off; a pair whose matrix
    is not positive definite or not finite takes no step and leaves the others alone."""
    g = torch.Generator().manual_seed(3)
    J = torch.randn(4, 6, 40, generator=g, dtype=F64)
    H = J @ J.transpose(1, 2)
    grad = torch.randn(4, 6, generator=g, dtype=F64)
    grad[1] *= 30  # a large step: the closed form's generic branch, not only the small-angle series
    T = se3_exp(0.2 * torch.randn(4, 6, generator=g, dtype=F64))
    active = torch.tensor([True, True, False, True])
    host = dense_module._update_numpy(H, grad, T, active, 1e-3)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dense_module, "HOST_FAST_PATHS", False)
        dev = dense_module._gauss_newton_update(H, grad, T, active, 1e-3)
    torch.testing.assert_close(host[0], dev[0], rtol=0, atol=1e-12)
    assert torch.equal(host[1], dev[1]) and torch.equal(host[2], dev[2])
    assert torch.equal(host[0][2], T[2])  # inactive: unchanged
    bad = H.clone()
    bad[0] = -torch.eye(6, dtype=F64)
    bad[3, 0, 0] = float("nan")
    out = dense_module._update_numpy(bad, grad, T, active, 1e-3)
    assert out[1].tolist() == [False, True, False, False]
    assert torch.equal(out[0][[0, 2, 3]], T[[0, 2, 3]])
    torch.testing.assert_close(out[0][1], dev[0][1], rtol=0, atol=1e-12)



def test_host_update_of_one_pair_equals_the_batched_one():
    """Tracking's single pair takes a scalar path (Cholesky as the definiteness test, the exp
    in scalars): the same poses and flags as the batched NumPy update, degenerate pairs too."""
    g = torch.Generator().manual_seed(4)
    J = torch.randn(5, 6, 40, generator=g, dtype=F64)
    H = J @ J.transpose(1, 2)
    H[2] = -torch.eye(6, dtype=F64)  # not positive definite
    H[3, 1, 1] = float("inf")
    H[4] = torch.zeros(6, 6, dtype=F64)  # singular
    grad = torch.randn(5, 6, generator=g, dtype=F64)
    grad[1] *= 30  # the generic branch of the closed form
    grad[0] *= 1e-7  # the small-angle series, and a step below tol
    T = se3_exp(0.2 * torch.randn(5, 6, generator=g, dtype=F64))
    for active in (True, False):
        act = torch.full((5,), active)
        batched = dense_module._update_numpy(H, grad, T, act, 1e-3)
        for b in range(5):
            one = dense_module._update_numpy(H[b : b + 1], grad[b : b + 1], T[b : b + 1], act[b : b + 1], 1e-3)
            torch.testing.assert_close(one[0], batched[0][b : b + 1], rtol=0, atol=1e-15)
            assert one[1].tolist() == batched[1][b : b + 1].tolist(), b
            assert one[2].tolist() == batched[2][b : b + 1].tolist(), b
    assert batched[1].tolist() == [False] * 5 and dense_module._update_numpy(H, grad, T, torch.ones(5, dtype=torch.bool), 1e-3)[1].tolist() == [True, True, False, False, False]

def test_host_scales_and_single_pair_loop_match_the_device_path(synthetic):
    """The CPU paths (the t-distribution scales in NumPy, one pair's iterations with Python
    bookkeeping) take the device path's decisions: the same steps, poses to 1e-7 m, scales to
    float round-off, including a pair with no valid residual (the floors)."""
    cam, rgb, depth, _ = synthetic
    cfg = DenseConfig()
    g = torch.Generator().manual_seed(5)
    rn = torch.randn(3, 2, 4000, generator=g) * torch.tensor([0.02, 0.005])[:, None]
    m = torch.rand(3, 2, 4000, generator=g) > 0.3
    m[2] = False
    rn = rn * m
    start = torch.tensor([[0.03, 0.004], [0.01, 0.01], [0.02, 0.002]])
    for st in (None, start):
        host = dense_module._scale(rn, m, dense_module.DenseRobust.STUDENT_T, cfg, st)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(dense_module, "HOST_FAST_PATHS", False)
            dev = dense_module._scale(rn, m, dense_module.DenseRobust.STUDENT_T, cfg, st)
        torch.testing.assert_close(host, dev, rtol=1e-5, atol=0)
        assert host.dtype == dev.dtype == rn.dtype
        # No valid residual: the floors.
        torch.testing.assert_close(host[2], torch.tensor([cfg.sigma_floor_photometric, cfg.sigma_floor_geometric]))
    fi = prepare_dense_frame(rgb[:1], depth[:1], cam, cfg)
    fj = prepare_dense_frame(rgb[1:], depth[1:], cam, cfg)
    T_init = se3_exp(torch.tensor([[0.01, 0.0, 0.0, 0.0, 0.01, 0.0], [0.0] * 6], dtype=F64))
    for b in range(2):
        host = register_dense_frames(fi, fj[b], T_init[b], cfg)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(dense_module, "HOST_FAST_PATHS", False)
            dev = register_dense_frames(fi, fj[b], T_init[b], cfg)
        assert host.iterations.tolist() == dev.iterations.tolist() and int(host.iterations[0]) > 2
        torch.testing.assert_close(host.T_ij, dev.T_ij, rtol=0, atol=1e-7)
        assert host.num_correspondences.tolist() == dev.num_correspondences.tolist()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_pyrdown_matches_kornia(dtype):
    x = torch.rand(2, 3, 24, 34, generator=torch.Generator().manual_seed(1), dtype=dtype)
    tol = dict(rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-13)
    torch.testing.assert_close(dense_module._pyrdown(x), kornia.geometry.transform.pyrdown(x), **tol)
    ones = torch.ones(1, 1, 16, 16, dtype=dtype)
    assert (dense_module._pyrdown(ones) >= 1.0 - 1e-6).all()  # the "inside" test of undistorted pyramids


def test_valid_aware_depth_reduction_by_three_matches_loop():
    g = torch.Generator().manual_seed(2)
    depth = 1.0 + torch.rand(1, 1, 10, 13, generator=g, dtype=F64) * 0.06
    depth[torch.rand(depth.shape, generator=g) < 0.3] = 0.0
    depth[0, 0, 0, 1] = 20.0  # out of range: ignored
    out = _reduce_depth(depth, 3, 0.04, 0.1, 10.0)
    assert out.shape == (1, 1, 3, 4)
    for r in range(3):
        for c in range(4):
            block = depth[0, 0, 3 * r : 3 * r + 3, 3 * c : 3 * c + 3].reshape(-1)
            v = block[(block >= 0.1) & (block <= 10.0)]
            ref = v.mean() if len(v) and v.max() - v.min() <= 0.04 * v.min() else torch.tensor(0.0, dtype=F64)
            torch.testing.assert_close(out[0, 0, r, c], ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("k, bounds", [(2, None), (2, (0.1, 10.0)), (3, (0.1, 10.0)), (3, None)])
def test_host_depth_reduction_equals_the_torch_one_bit_for_bit(k, bounds):
    """The OpenCV path of ``_reduce_depth`` (CPU, float32) gives the torch path's bits, with
    holes, NaN, +-inf, negative, out-of-range and disagreeing blocks, on a strided batch."""
    g = torch.Generator().manual_seed(21)
    d = torch.linspace(0.8, 4.0, 83).expand(2, 1, 61, 83) + 0.02 * torch.rand(2, 1, 61, 83, generator=g)  # mostly agreeing
    u = torch.rand(d.shape, generator=g)
    d[u < 0.10] = 0.0
    d[(u > 0.10) & (u < 0.12)] = float("nan")
    d[(u > 0.12) & (u < 0.13)] = float("inf")
    d[(u > 0.13) & (u < 0.14)] = -1.0
    d[(u > 0.14) & (u < 0.15)] = 20.0
    d[(u > 0.15) & (u < 0.16)] = 0.05
    d[:, :, 10:20, 10:30] = 1.0 + 3 * torch.rand(2, 1, 10, 20, generator=g)  # disagreeing blocks
    d = d[:, :, :, 1:]  # a strided view
    lo, hi = bounds if bounds else (None, None)
    host = dense_module._reduce_depth(d, k, 0.05, lo, hi)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dense_module, "HOST_FAST_PATHS", False)
        ref = dense_module._reduce_depth(d, k, 0.05, lo, hi)
    assert host.shape == ref.shape == (2, 1, 61 // k, 82 // k)
    assert torch.equal(host.view(torch.int32), ref.view(torch.int32))
    assert 0.2 < (ref > 0).float().mean() < 0.98  # both outcomes occur
