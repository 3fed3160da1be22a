import math

import cv2
import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, DTypeError, InvalidValueError, ShapeError
from torchslam.geometry import so3_exp
from torchslam.kcc import (
    KCCConfig,
    choose_resolution,
    depth_translation,
    grey_from_rgb,
    kcc_features,
    kcc_predict,
    kcc_train,
    orthographic_project,
    rgbd_to_points,
    sample_grey,
)

from tests._helpers import seeded


def brute_zbuffer(points, grey, valid, R, r, center, H, W):
    """Per-point loop: nearest z wins, ties to the lower index. NumPy float64 oracle."""
    B, N, _ = points.shape
    depth = np.zeros((B, H, W))
    out_grey = np.zeros((B, H, W))
    best = np.full((B, H, W), -1)
    for b in range(B):
        p = points[b] @ R[b].T
        for n in range(N):
            if not valid[b, n]:
                continue
            u = (p[n, 0] - center[b, 0]) / r[b] + W / 2
            v = (p[n, 1] - center[b, 1]) / r[b] + H / 2
            if not (0 <= u < W and 0 <= v < H):
                continue
            col, row = int(math.floor(u)), int(math.floor(v))
            if best[b, row, col] < 0 or p[n, 2] < depth[b, row, col]:
                best[b, row, col] = n
                depth[b, row, col] = p[n, 2]
                out_grey[b, row, col] = grey[b, n]
    return out_grey, depth, best >= 0


def test_zbuffer_planted_nearest_wins_ties_to_lowest_index():
    # r = 1 m/px, 4 x 5 image: pixel (col, row) = (floor(x + 2.5), floor(y + 2)).
    pts = torch.tensor(
        [
            [-1.2, 0.3, 3.0],  # pixel (1, 2), far
            [-1.1, 0.4, 1.5],  # pixel (1, 2), nearest: wins
            [-1.3, 0.2, 2.0],  # pixel (1, 2)
            [-1.2, 0.3, 0.5],  # pixel (1, 2), even nearer but invalid
            [1.6, -1.9, 2.0],  # pixel (4, 0), tie ...
            [1.7, -1.8, 2.0],  # ... with this one: the lower index wins
            [10.0, 0.0, 1.0],  # outside the image
            [2.5, 0.0, 1.0],  # x = W/2 exactly: outside (half-open pixel range)
            [-2.5, -2.0, 1.0],  # the corner (0, 0): inside
        ],
        dtype=torch.float64,
    )[None]
    grey = torch.tensor([[0.1, 0.7, 0.3, 0.9, 0.2, 0.8, 0.5, 0.5, 0.4]], dtype=torch.float64)
    valid = torch.ones(1, 9, dtype=torch.bool)
    valid[0, 3] = False
    out = orthographic_project(pts, grey, valid, None, torch.ones(1, dtype=torch.float64), size=(4, 5))
    assert out.valid.sum() == 3
    assert out.valid[0, 2, 1] and out.grey[0, 2, 1] == 0.7 and out.depth[0, 2, 1] == 1.5
    assert out.valid[0, 0, 4] and out.grey[0, 0, 4] == 0.2
    assert out.valid[0, 0, 0] and out.grey[0, 0, 0] == 0.4
    assert (out.grey[~out.valid] == 0).all() and (out.depth[~out.valid] == 0).all()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_zbuffer_equals_per_point_loop_with_rotation_and_center(dtype):
    gen = seeded(1)
    B, N, H, W = 3, 400, 6, 7
    pts = torch.randn(B, N, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64)
    pts[..., 2] += 2.0
    pts = (pts * 64).round() / 64  # dyadic values: float32 and float64 agree on every pixel and tie
    grey = torch.rand(B, N, generator=gen, dtype=torch.float64)
    valid = torch.rand(B, N, generator=gen) > 0.2
    R = so3_exp(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2], [0.0, 0.0, math.pi]], dtype=torch.float64))
    R = R.round()  # exact quarter turns
    r = torch.tensor([0.125, 0.25, 0.0625], dtype=torch.float64)
    center = torch.tensor([[0.0, 0.0], [0.25, -0.125], [-0.5, 0.0]], dtype=torch.float64)
    ref_grey, ref_depth, ref_valid = brute_zbuffer(
        pts.numpy(), grey.numpy(), valid.numpy(), R.numpy(), r.numpy(), center.numpy(), H, W
    )
    out = orthographic_project(pts.to(dtype), grey.to(dtype), valid, R.to(dtype), r.to(dtype), (H, W), center.to(dtype))
    assert out.grey.dtype == dtype and out.valid.shape == (B, H, W)
    assert ref_valid.sum() > 40 and (~ref_valid).sum() > 5  # collisions and holes both occur
    assert np.array_equal(out.valid.numpy(), ref_valid)
    np.testing.assert_allclose(out.grey.double().numpy(), ref_grey, atol=1e-6)
    np.testing.assert_allclose(out.depth.double().numpy(), ref_depth, atol=1e-6)
    # Batched equals per item.
    for b in range(B):
        one = orthographic_project(
            pts[b : b + 1].to(dtype), grey[b : b + 1].to(dtype), valid[b : b + 1], R[b : b + 1].to(dtype),
            r[b : b + 1].to(dtype), (H, W), center[b : b + 1].to(dtype),
        )
        # the same pixels win; grey and depth to round-off (the rotation is a batched matmul)
        assert torch.equal(one.valid[0], out.valid[b])
        tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(one.grey[0], out.grey[b], **tol)
        torch.testing.assert_close(one.depth[0], out.depth[b], **tol)


def test_colour_is_rendered_with_the_grey_winners():
    """``colour`` channels take the same z-buffer winners as grey: each channel equals a grey projection of it."""
    gen = seeded(3)
    B, N, H, W = 2, 500, 6, 7
    pts = torch.randn(B, N, 3, generator=gen) * 0.4
    pts[..., 2] += 2.0
    pts = (pts * 16).round() / 16  # many exact z ties
    valid = torch.rand(B, N, generator=gen) > 0.2
    colour = torch.rand(B, 3, N, generator=gen)
    r = torch.tensor([0.125, 0.25])
    grey = colour.mean(dim=1)
    out = orthographic_project(pts, grey, valid, None, r, (H, W), colour=colour)
    assert out.colour.shape == (B, 3, H, W)
    for c in range(3):
        ref = orthographic_project(pts, colour[:, c], valid, None, r, (H, W))
        assert torch.equal(out.colour[:, c], ref.grey) and torch.equal(out.valid, ref.valid)
    assert orthographic_project(pts, grey, valid, None, r, (H, W)).colour is None
    with pytest.raises(ShapeError, match="colour"):
        orthographic_project(pts, grey, valid, None, r, (H, W), colour=colour[:, :, :-1])


def test_projection_is_differentiable_in_grey_and_depth_of_the_winners():
    gen = seeded(2)
    pts = torch.rand(1, 300, 3, generator=gen, dtype=torch.float64) * 2 - 1
    pts[..., 2] += 3.0
    pts.requires_grad_()
    grey = torch.rand(1, 300, generator=gen, dtype=torch.float64, requires_grad=True)
    valid = torch.ones(1, 300, dtype=torch.bool)
    out = orthographic_project(pts, grey, valid, None, torch.tensor([0.25], dtype=torch.float64), (8, 8))
    (out.grey.sum() + 2 * out.depth.sum()).backward()
    _, _, ref_valid = brute_zbuffer(
        pts.detach().numpy(), grey.detach().numpy(), valid.numpy(), np.eye(3)[None], [0.25], np.zeros((1, 2)), 8, 8
    )
    winners = grey.grad[0] > 0
    assert winners.sum() == ref_valid.sum() == out.valid.sum()
    assert set(grey.grad[0].unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(pts.grad[0, :, 2] == 2.0, winners) and (pts.grad[0, :, :2] == 0).all()


def test_choose_resolution_is_the_coverage_order_statistic(tum_rgbd):
    rgb, depth, intr = tum_rgbd
    pts, grey, valid = rgbd_to_points(rgb, depth, intr)
    pts = torch.cat([pts, pts])
    valid = torch.cat([valid, torch.zeros_like(valid)])  # second item: no valid point at all
    grey = torch.cat([grey, grey])
    H, W = 360, 480
    r = choose_resolution(pts, valid, (H, W), coverage=0.8, sample_step=25)
    assert math.isnan(r[1].item())
    # NumPy oracle on the sampled points.
    s = pts[0, ::25].double().numpy()
    ok = valid[0, ::25].numpy()
    need = np.maximum(np.abs(s[ok, 0]) / (W / 2), np.abs(s[ok, 1]) / (H / 2))
    k = math.ceil(0.8 * need.size) - 1
    assert r[0].item() == pytest.approx(np.sort(need)[k] * (1 + 1e-6), rel=1e-6)
    # At least 80 % of the sampled points, and about 80 % of all points, render inside.
    inside = np.mean(need <= r[0].item())
    assert 0.8 <= inside <= 0.8 + 2.0 / need.size
    p = pts[0, valid[0]].double()
    frac_all = ((p[:, 0].abs() < r[0] * W / 2) & (p[:, 1].abs() < r[0] * H / 2)).double().mean()
    assert abs(frac_all.item() - 0.8) < 0.01
    # A larger image at the same coverage needs a finer resolution, an offset centre a coarser one.
    r_big = choose_resolution(pts[:1], valid[:1], (720, 960))
    assert r_big[0] == pytest.approx(r[0].item() / 2, rel=1e-5)
    r_off = choose_resolution(pts[:1], valid[:1], (H, W), center=torch.tensor([[0.3, 0.0]]))
    assert r_off[0] > r[0]


def test_planted_translation_and_rotation_recovered_through_orthographic_images(tum_rgbd):
    """Sign convention end to end: a camera displaced by d from the keyframe sees content moved by -d."""
    rgb, depth, intr = tum_rgbd
    cfg = KCCConfig()
    size = (cfg.ortho_height, cfg.ortho_width)
    pts_k, grey, valid = rgbd_to_points(rgb.double(), depth.double(), intr.double())
    r = choose_resolution(pts_k, valid, size)
    kf = orthographic_project(pts_k, grey, valid, None, r, size)
    # Frame cameras displaced by d and rotated by R_ki (attitude known): p_i = R_ki^T (p_k - d).
    d = torch.tensor(
        [
            [7 * r.item(), -4 * r.item(), 0.0],  # an exact integer image shift
            [0.0213, -0.0161, 0.0],
            [-0.0137, 0.0242, 0.031],
            [0.0311, 0.0087, -0.042],
        ],
        dtype=torch.float64,
    )
    phi = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.05, -0.03, 0.02], [-0.04, 0.06, -0.05]], dtype=torch.float64)
    R = so3_exp(phi)
    B = d.shape[0]
    pts_i = torch.einsum("bji,bnj->bni", R, pts_k - d[:, None, :])  # R^T (p - d)
    rk = r.expand(B)
    grey_b, valid_b = grey.expand(B, -1).float(), valid.expand(B, -1)
    fr = orthographic_project(pts_i.float(), grey_b, valid_b, R.float(), rk.float(), size)
    kfeat = kcc_features(kf.grey, kf.depth, kf.valid, cfg.channel_norm, cfg.fill_holes).float()
    filt = kcc_train(kfeat.expand(B, -1, -1, -1), cfg.sigma, cfg.lam)
    xfeat = kcc_features(fr.grey, fr.depth, fr.valid, cfg.channel_norm, cfg.fill_holes)
    pred = kcc_predict(xfeat, filt, cfg.sigma, rk.float())
    err_px = (pred.t_xy.double() + d[:, :2]).abs() / r
    assert err_px.max() < 0.2, err_px  # within r_k / 5
    assert torch.equal(pred.index[0], torch.tensor([-7, 4]))
    assert (pred.psr > cfg.T_M).all()
    kf32 = orthographic_project(pts_k.float().expand(B, -1, -1), grey_b, valid_b, None, rk.float(), size)
    dz = depth_translation(fr, kf32, pred.index, cfg.T_c, cfg.T_d)
    assert dz.ok.all()
    torch.testing.assert_close(dz.t_z.double(), -d[:, 2], atol=1.5e-3, rtol=0)


def test_grey_from_rgb_matches_opencv_and_points_follow_backprojection(tum_rgbd):
    rgb, depth, intr = tum_rgbd
    grey = grey_from_rgb(rgb)
    ref = cv2.cvtColor(rgb[0].permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY)
    np.testing.assert_allclose(grey[0].numpy(), ref.reshape(-1), atol=1e-6)
    pts, g, valid = rgbd_to_points(rgb, depth, intr)
    assert pts.shape == (1, 480 * 640, 3) and torch.equal(g, grey)
    assert torch.equal(valid[0], (depth[0, 0] > 0).reshape(-1))


def test_nonpositive_or_nan_resolution_gives_an_empty_image():
    pts = torch.rand(3, 50, 3, generator=seeded(3)) - 0.5
    bad_r = torch.tensor([0.0, -0.1, math.nan])
    out = orthographic_project(pts, torch.rand(3, 50), torch.ones(3, 50, dtype=torch.bool), None, bad_r, (4, 4))
    assert not out.valid.any() and torch.isfinite(out.grey).all() and torch.isfinite(out.depth).all()


def test_bad_inputs_raise():
    pts = torch.rand(2, 10, 3)
    grey = torch.rand(2, 10)
    valid = torch.ones(2, 10, dtype=torch.bool)
    r = torch.ones(2)
    with pytest.raises(ShapeError, match=r"points: expected \(B, N, 3\), got \(2, 10, 2\)"):
        orthographic_project(torch.rand(2, 10, 2), grey, valid, None, r)
    with pytest.raises(ShapeError, match="grey"):
        orthographic_project(pts, torch.rand(2, 11), valid, None, r)
    with pytest.raises(DTypeError, match="valid"):
        orthographic_project(pts, grey, valid.float(), None, r)
    with pytest.raises(ShapeError, match="rotation"):
        orthographic_project(pts, grey, valid, torch.eye(3), r)
    with pytest.raises(ShapeError, match="resolution"):
        orthographic_project(pts, grey, valid, None, torch.ones(3))
    with pytest.raises(ShapeError, match="center"):
        orthographic_project(pts, grey, valid, None, r, center=torch.zeros(2, 3))
    with pytest.raises(ShapeError, match="size"):
        orthographic_project(pts, grey, valid, None, r, size=(0, 4))
    with pytest.raises(ConfigError, match="coverage"):
        choose_resolution(pts, valid, coverage=1.5)
    with pytest.raises(ConfigError, match="sample_step"):
        choose_resolution(pts, valid, sample_step=0)
    with pytest.raises(DTypeError, match="points"):
        choose_resolution(pts.long(), valid)
    with pytest.raises(ShapeError, match="rgb"):
        grey_from_rgb(torch.rand(1, 4, 8, 8))


def test_sample_grey_matches_scipy_bilinear_reprojection():
    """Points rotated into another camera, projected and sampled bilinearly; scipy is the oracle."""
    from scipy.ndimage import map_coordinates
    from scipy.spatial.transform import Rotation

    B, H, W = 2, 24, 32
    g = seeded(3)
    rgb = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    depth = 1.0 + torch.rand(B, 1, H, W, generator=g, dtype=torch.float64)
    depth[0, 0, 5, 7] = 0.0
    intr = torch.tensor([[30.0, 31.0, 15.2, 11.7], [28.0, 29.5, 16.1, 12.3]], dtype=torch.float64)
    points, grey0, valid = rgbd_to_points(rgb, depth, intr)
    R = torch.from_numpy(Rotation.from_rotvec([[0.02, -0.03, 0.01], [-0.04, 0.01, 0.05]]).as_matrix())
    grey, ok = sample_grey(rgb, points, valid, R, intr)
    img = grey_from_rgb(rgb).view(B, H, W).numpy()
    for b in range(B):
        q = points[b].numpy() @ R[b].numpy().T
        fx, fy, cx, cy = intr[b].numpy()
        z = np.where(q[:, 2] > 0, q[:, 2], 1.0)  # the depth hole back-projects to z = 0
        u = fx * q[:, 0] / z + cx
        v = fy * q[:, 1] / z + cy
        inside = valid[b].numpy() & (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
        np.testing.assert_array_equal(ok[b].numpy(), inside)
        # Border pixels extend outwards by half a pixel (edge replication), as mode="nearest" does.
        ref = map_coordinates(img[b], np.stack([v, u]), order=1, mode="nearest")
        np.testing.assert_allclose(grey[b].numpy()[inside], ref[inside], atol=1e-6)
        assert (grey[b].numpy()[~inside] == 0).all()
    assert not bool(ok[0].view(H, W)[5, 7])
    assert 0.3 * H * W < int(ok.sum()) < B * H * W  # some fall outside, most stay inside
    # No rotation: the colour pixel of each point, unchanged.
    same, ok_same = sample_grey(rgb, points, valid, torch.eye(3, dtype=torch.float64).expand(B, 3, 3), intr)
    torch.testing.assert_close(same[valid], grey0[valid], atol=1e-6, rtol=0)
    assert torch.equal(ok_same, valid)
    with pytest.raises(ShapeError, match="points"):
        sample_grey(rgb, points[:, :-1], valid[:, :-1], R, intr)


def test_rgbd_to_points_is_bit_identical_to_backproject_depth_across_cameras():
    """The cached per-pixel factors must give exactly geometry.backproject_depth, per camera."""
    from torchslam.geometry import backproject_depth

    g = seeded(11)
    for dtype in (torch.float32, torch.float64):
        rgb = torch.rand(2, 3, 12, 16, generator=g, dtype=dtype)
        depth = 0.5 + 3 * torch.rand(2, 1, 12, 16, generator=g, dtype=dtype)
        depth[0, 0, 3, 4] = 0.0
        depth[1, 0, 7, 1] = float("nan")
        for intr in (
            torch.tensor([[20.0, 21.0, 7.5, 5.5], [19.0, 22.0, 8.1, 6.2]], dtype=dtype),
            torch.tensor([[20.0, 21.0, 7.5, 5.5], [19.0, 22.0, 8.1, 6.3]], dtype=dtype),  # cache must miss
            torch.tensor([20.0, 21.0, 7.5, 5.5], dtype=dtype),
        ):
            for _ in range(2):  # second call hits the cache
                pts, grey, valid = rgbd_to_points(rgb, depth, intr)
                ref_pts, ref_valid = backproject_depth(depth, intr)
                assert torch.equal(pts, ref_pts) and torch.equal(valid, ref_valid)
                assert torch.equal(grey, grey_from_rgb(rgb))


def test_rgbd_to_points_along_undistorted_rays_and_distorted_sample_grey():
    """Rays from geometry.undistorted_rays; sampling through the lens matches OpenCV + scipy."""
    from scipy.ndimage import map_coordinates
    from scipy.spatial.transform import Rotation

    from torchslam.geometry import PinholeCamera, undistorted_rays

    B, H, W = 2, 24, 32
    cam = PinholeCamera(30.0, 31.0, 15.2, 11.7, W, H, (0.26, -0.95, -0.005, 0.003, 1.16))
    intr = cam.as_tensor(torch.float64)
    g = seeded(5)
    rgb = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    depth = 1.0 + torch.rand(B, 1, H, W, generator=g, dtype=torch.float64)
    depth[1, 0, 4, 6] = 0.0
    rays = undistorted_rays(cam)
    points, grey0, valid = rgbd_to_points(rgb, depth, intr, rays=rays)
    z = depth.flatten(1)
    expect = torch.stack([rays[:, 0] * z, rays[:, 1] * z, z], dim=-1)
    assert torch.equal(points[valid], expect[valid]) and int(valid.sum()) == B * H * W - 1
    assert torch.equal(grey0, grey_from_rgb(rgb))
    # Without rotation each point lands back on its own pixel through the lens.
    eye = torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
    same, ok_same = sample_grey(rgb, points, valid, eye, intr, grey_image=grey0, distortion=cam.distortion)
    torch.testing.assert_close(same[valid], grey0[valid], atol=1e-6, rtol=0)
    assert torch.equal(ok_same, valid)
    # A rotation: OpenCV projects with the distortion, scipy samples bilinearly.
    R = torch.from_numpy(Rotation.from_rotvec([[0.02, -0.03, 0.01], [-0.04, 0.01, 0.05]]).as_matrix())
    grey, ok = sample_grey(rgb, points, valid, R, intr, distortion=cam.distortion)
    plain, _ = sample_grey(rgb, points, valid, R, intr)
    img = grey0.view(B, H, W).numpy()
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    for b in range(B):
        m = valid[b].numpy()
        q = points[b].numpy() @ R[b].numpy().T
        uv, _ = cv2.projectPoints(q[m], np.zeros(3), np.zeros(3), K, np.asarray(cam.distortion))
        u, v = uv.reshape(-1, 2).T
        inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
        np.testing.assert_array_equal(ok[b].numpy()[m], inside)
        ref = map_coordinates(img[b], np.stack([v, u]), order=1, mode="nearest")
        np.testing.assert_allclose(grey[b].numpy()[m][inside], ref[inside], atol=1e-6)
    assert not torch.allclose(grey[ok], plain[ok], atol=1e-3)  # the lens matters here
    with pytest.raises(ShapeError, match="rays"):
        rgbd_to_points(rgb, depth, intr, rays=rays[:-1])


@pytest.mark.parametrize("distorted", [False, True])
def test_sample_grey_rotated_equals_per_point_sampling_to_hundredths_of_a_pixel(distorted):
    """The rotation-only warp, interpolated between nodes, against the per-point projection."""
    from scipy.spatial.transform import Rotation

    from torchslam.geometry import PinholeCamera, undistorted_rays
    from torchslam.kcc import sample_grey_rotated

    H, W = 120, 160
    dist = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633) if distorted else None
    cam = PinholeCamera(129.3, 129.1, 79.6, 63.8, W, H, dist)  # TUM freiburg1 at a quarter size
    intr = cam.as_tensor(torch.float64)[None].expand(2, 4)
    rays = undistorted_rays(cam) if distorted else None
    # Grey ramps: a sampled value is a position, grey = (u + 2 v) / 1000.
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rgb = ((u + 2 * v) / 1000).expand(2, 3, H, W).contiguous()
    depth = (1.0 + torch.rand(2, 1, H, W, generator=seeded(7), dtype=torch.float64))
    points, grey0, valid = rgbd_to_points(rgb, depth, intr, rays=rays)
    R = torch.from_numpy(Rotation.from_rotvec([[0.004, -0.006, 0.002], [-0.015, 0.01, 0.008]]).as_matrix())
    exact, ok_e = sample_grey(rgb, points, valid, R, intr, grey_image=grey0, distortion=dist)
    # Nodes 2 px apart at this quarter size: the default 8 px at 640 x 480.
    fast, ok_f = sample_grey_rotated(rgb, valid, R, intr, rays=rays, grey_image=grey0, distortion=dist, step=2)
    both = ok_e & ok_f
    assert int((ok_e != ok_f).sum()) <= 2  # only points on the image border can differ
    # |d grey| = |du + 2 dv| / 1000 bounds the position error in pixels (up to the factor 2).
    err = (exact - fast).abs() * 1000
    assert float(err[0][both[0]].max()) < 0.01  # a 0.4 degree rotation
    assert float(err[1][both[1]].max()) < 0.025  # 1.1 degrees
    assert bool((fast[~ok_f] == 0).all())
    # No rotation: every pixel keeps its own grey value.
    eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    same, ok_same = sample_grey_rotated(rgb, valid, eye, intr, rays=rays, grey_image=grey0, distortion=dist)
    # (to 0.001 px through the lens: the node rays are interpolated in the per-pixel ray image)
    torch.testing.assert_close(same[valid], grey0[valid], atol=1e-6 if distorted else 1e-12, rtol=0)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    with pytest.raises(InvalidValueError, match="behind the camera"):
        sample_grey_rotated(rgb, valid, flip.expand(2, 3, 3), intr)
    # With the points, an item the warp cannot serve is sampled per point; the others are not.
    mixed = torch.stack([R[0], flip])
    g, ok = sample_grey_rotated(rgb, valid, mixed, intr, rays=rays, grey_image=grey0, distortion=dist, step=2, points=points)
    g_ref, ok_ref = sample_grey(rgb[1:], points[1:], valid[1:], flip[None], intr[1:], grey_image=grey0[1:], distortion=dist)
    assert torch.equal(g[1], g_ref[0]) and torch.equal(ok[1], ok_ref[0])
    assert torch.equal(g[0], fast[0]) and torch.equal(ok[0], ok_f[0])
