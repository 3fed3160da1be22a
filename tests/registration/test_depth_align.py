"""The sparse registration's refinement against the keyframe's depth (``registration.depth_align``)."""

from __future__ import annotations

import pytest
import torch

from torchslam.data import SyntheticConfig, generate_sequence
from torchslam.geometry import PinholeCamera, se3_exp, se3_inverse, undistorted_rays
from torchslam.registration.depth_align import refine_with_depth, sample_depth_points
from torchslam.registration.sparse import frame_features, register_sparse

F64 = torch.float64


def _pose_error(T: torch.Tensor, T_ref: torch.Tensor) -> tuple[float, float]:
    E = se3_inverse(T_ref) @ T
    cos = ((E[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return float(E[:3, 3].norm()), float(torch.rad2deg(torch.acos(cos)))


@pytest.fixture(scope="module")
def pair():
    """Two synthetic frames (noise-free depth), their ORB registration and the true pose."""
    seq = generate_sequence(SyntheticConfig(frames=9, width=320, height=240, trajectory="handheld", batch_size=9))
    fi, fj = seq[0], seq[8]
    feats_i = frame_features(fi.rgb, fi.depth, seq.camera)
    feats_j = frame_features(fj.rgb, fj.depth, seq.camera)
    res = register_sparse(feats_i, feats_j)
    assert bool(res.success[0])
    T_gt = se3_inverse(fi.T_wc.to(F64)) @ fj.T_wc.to(F64)
    return seq, fi, fj, res, T_gt


def test_sample_depth_points_lie_on_the_valid_pixels_rays():
    cam = PinholeCamera(100.0, 100.0, 31.5, 23.5, 64, 48)
    depth = torch.full((1, 48, 64), 2.0)
    depth[0, :, :32] = 0  # no depth on the left half
    rays = undistorted_rays(cam)
    pts = sample_depth_points(depth, rays, 48, 0.1, 10.0)
    s = round((64 * 48 / 48) ** 0.5)  # lattice step 8
    assert len(pts) == (48 // s) * (32 // s)
    assert torch.all(pts[:, 2] == 2.0)
    u = pts[:, 0] / pts[:, 2] * cam.fx + cam.cx
    v = pts[:, 1] / pts[:, 2] * cam.fy + cam.cy
    assert torch.all(u >= 32) and torch.allclose(u % s, torch.full_like(u, s // 2), atol=1e-9)
    assert torch.allclose(v % s, torch.full_like(v, s // 2), atol=1e-9)


def test_a_perturbed_pose_returns_to_the_planted_one(pair):
    """Noise-free depth, exact matches: from 1 cm and 0.6 degrees off, three steps more than halve
    the error and six land within 1 mm and 0.05 degrees (the rendered depth's own minimum lies
    about 0.6 mm from the true pose: 0.2 mm depth steps and bilinear sampling across surfaces)."""
    seq, fi, fj, res, T_gt = pair
    rays = undistorted_rays(seq.camera)
    pts = sample_depth_points(fj.depth, rays, 3000, 0.1, 10.0)
    # The ORB matches at their true positions (exact correspondences), the start perturbed.
    p_j = res.points_j[0]
    p_i = p_j @ T_gt[:3, :3].T + T_gt[:3, 3]
    inl = res.inliers[0]
    T0 = se3_exp(torch.tensor([0.006, -0.005, 0.006, 0.006, -0.004, 0.005], dtype=F64)) @ T_gt
    assert _pose_error(T0, T_gt)[0] > 0.009
    T3, used = refine_with_depth(T0, fi.depth, seq.camera, pts, p_i, p_j, inl, 3)
    assert used > 1000
    assert _pose_error(T3, T_gt)[0] < 0.5 * _pose_error(T0, T_gt)[0]
    T, _ = refine_with_depth(T0, fi.depth, seq.camera, pts, p_i, p_j, inl, 6)
    dt, dr = _pose_error(T, T_gt)
    assert dt < 1e-3 and dr < 0.05, (dt, dr)


def test_refinement_improves_the_orb_pose(pair):
    seq, fi, fj, res, T_gt = pair
    pts = sample_depth_points(fj.depth, undistorted_rays(seq.camera), 3000, 0.1, 10.0)
    T, used = refine_with_depth(res.T_ij[0], fi.depth, seq.camera, pts, res.points_i[0], res.points_j[0], res.inliers[0], 3)
    e_orb, e_ref = _pose_error(res.T_ij[0], T_gt), _pose_error(T, T_gt)
    assert used > 1000
    assert e_ref[0] < 0.5 * e_orb[0], (e_orb, e_ref)


def test_host_path_matches_the_device_path(pair, monkeypatch):
    """The NumPy steps are the torch path's, to round-off."""
    import torchslam.registration.depth_align as module

    seq, fi, fj, res, _ = pair
    pts = sample_depth_points(fj.depth, undistorted_rays(seq.camera), 3000, 0.1, 10.0)
    args = (res.T_ij[0], fi.depth, seq.camera, pts, res.points_i[0], res.points_j[0], res.inliers[0], 3)
    host = refine_with_depth(*args)
    monkeypatch.setattr(module, "numpy_viewable", lambda x: False)
    dev = refine_with_depth(*args)
    torch.testing.assert_close(host[0], dev[0], rtol=0, atol=1e-12)
    assert host[1] == dev[1]


def _plane_depth(cam: PinholeCamera, T_wc: torch.Tensor | None = None, distortion=None) -> torch.Tensor:
    """Depth of the plane z = 2 - 0.3 x + 0.2 y (camera of ``T_wc`` in the plane's frame) per pixel."""
    rays = undistorted_rays(cam).to(F64)
    d = torch.cat([rays, torch.ones(len(rays), 1, dtype=F64)], -1)  # (HW, 3) direction, z = 1
    T = torch.eye(4, dtype=F64) if T_wc is None else T_wc
    o, dw = T[:3, 3], d @ T[:3, :3].T
    # plane n . p = c with n = (0.3, -0.2, 1), c = 2
    n = torch.tensor([0.3, -0.2, 1.0], dtype=F64)
    s = (2.0 - n @ o) / (dw @ n)
    return s.reshape(1, cam.height, cam.width).float()


def test_distorted_camera_recovers_the_pose():
    """With lens distortion the projection and its Jacobian go through the distortion model."""
    cam = PinholeCamera(260.0, 260.0, 160.0, 120.0, 320, 240, distortion=(0.26, -0.95, -0.005, 0.003, 1.16))
    # A corrugated surface (a plane with a ridge) so the depth constrains more than 3 directions,
    # and ORB-like matches for the rest.
    g = torch.Generator().manual_seed(3)
    T_gt = se3_exp(torch.tensor([0.02, -0.01, 0.015, 0.01, 0.02, -0.01], dtype=F64))
    rays = undistorted_rays(cam).to(F64)

    def depth_of(T_wc):
        d = torch.cat([rays, torch.ones(len(rays), 1, dtype=F64)], -1)
        o, dw = T_wc[:3, 3], d @ T_wc[:3, :3].T
        # bumpy surface z = 2 + 0.1 sin(4 x) cos(3 y), intersected by fixed-point iteration
        s = (2.0 - o[2]) / dw[:, 2]
        for _ in range(30):
            p = o + s[:, None] * dw
            zs = 2.0 + 0.1 * torch.sin(4 * p[:, 0]) * torch.cos(3 * p[:, 1])
            s = (zs - o[2]) / dw[:, 2]
        return s.reshape(1, cam.height, cam.width).float()

    depth_i = depth_of(torch.eye(4, dtype=F64))
    depth_j = depth_of(T_gt)
    pts = sample_depth_points(depth_j, undistorted_rays(cam), 3000, 0.1, 10.0)
    p_j = pts[torch.randperm(len(pts), generator=g)[:200]]
    p_i = p_j @ T_gt[:3, :3].T + T_gt[:3, 3]
    T0 = se3_exp(torch.tensor([0.005, 0.004, -0.006, -0.004, 0.005, 0.003], dtype=F64)) @ T_gt
    T, used = refine_with_depth(T0, depth_i, cam, pts, p_i, p_j, torch.ones(200, dtype=torch.bool), 4)
    dt, dr = _pose_error(T, T_gt)
    assert used > 1000
    assert dt < 5e-4 and dr < 0.02, (dt, dr)
    # The same start with the distortion ignored in the projection lands farther away.
    flat = PinholeCamera(260.0, 260.0, 160.0, 120.0, 320, 240)
    T_flat, _ = refine_with_depth(T0, depth_i, flat, pts, p_i, p_j, torch.ones(200, dtype=torch.bool), 4)
    assert _pose_error(T_flat, T_gt)[0] > 3 * dt


def test_a_plane_keeps_the_directions_it_cannot_see_from_the_orb_matches():
    """Depth of one plane pins 3 of 6 directions; the ORB matches hold the other 3 (no slide)."""
    cam = PinholeCamera(260.0, 260.0, 159.5, 119.5, 320, 240)
    T_gt = se3_exp(torch.tensor([0.03, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64))  # slide along x
    depth_i = _plane_depth(cam)
    depth_j = _plane_depth(cam, T_gt)
    pts = sample_depth_points(depth_j, undistorted_rays(cam), 3000, 0.1, 10.0)
    p_j = pts[::15]
    p_i = p_j @ T_gt[:3, :3].T + T_gt[:3, 3]
    T0 = se3_exp(torch.tensor([0.002, -0.002, 0.003, 0.002, -0.001, 0.002], dtype=F64)) @ T_gt
    T, used = refine_with_depth(T0, depth_i, cam, pts, p_i, p_j, torch.ones(len(p_j), dtype=torch.bool), 4)
    assert used > 1000
    dt, dr = _pose_error(T, T_gt)
    assert dt < 2e-4 and dr < 0.01, (dt, dr)


def test_too_few_depth_points_keep_the_pose():
    cam = PinholeCamera(260.0, 260.0, 159.5, 119.5, 320, 240)
    depth = _plane_depth(cam)
    pts = sample_depth_points(depth, undistorted_rays(cam), 50, 0.1, 10.0)
    T0 = se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64))
    T, used = refine_with_depth(T0, depth, cam, pts, pts, pts, torch.ones(len(pts), dtype=torch.bool), 3)
    assert used == 0
    assert torch.equal(T, T0)


@pytest.mark.parametrize("distortion", [None, (0.26, -0.95, -0.005, 0.003, 1.16)], ids=["pinhole", "fr1-lens"])
def test_depth_residual_jacobian_equals_central_differences(distortion):
    """``d r_Z / d xi`` (left update, translation first) through the projection, the lens model and
    the bilinear depth against central differences of the residual itself (float64)."""
    import numpy as np

    from torchslam.registration.depth_align import _depth_terms_numpy

    cam = PinholeCamera(260.0, 260.0, 160.0, 120.0, 320, 240, distortion=distortion)
    vv, uu = np.meshgrid(np.arange(240.0), np.arange(320.0), indexing="ij")
    flat = (2.0 + 0.2 * np.sin(uu / 30.0) * np.cos(vv / 25.0)).reshape(-1)
    g = np.random.default_rng(0)
    P = np.stack([g.uniform(-0.6, 0.6, 500), g.uniform(-0.45, 0.45, 500), g.uniform(1.8, 2.2, 500)])
    T = se3_exp(torch.tensor([0.01, -0.02, 0.01, 0.02, -0.01, 0.01], dtype=F64)).numpy()
    J = np.empty((6, 500))
    r0, ok, _ = _depth_terms_numpy(T, P, flat, 320, 240, cam, 0.1, 0.2, J)
    h = 1e-7
    agree = ok.copy()
    num = np.empty_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        rp, okp, _ = _depth_terms_numpy(se3_exp(torch.tensor(d)).numpy() @ T, P, flat, 320, 240, cam, 0.1, 0.2, np.empty((6, 500)))
        rm, okm, _ = _depth_terms_numpy(se3_exp(torch.tensor(-d)).numpy() @ T, P, flat, 320, 240, cam, 0.1, 0.2, np.empty((6, 500)))
        num[k] = (rp - rm) / (2 * h)
        agree &= okp & okm
    assert agree.sum() > 300
    close = np.isclose(J, num, rtol=1e-4, atol=1e-6).all(0) | ~agree
    # A point whose step crosses a pixel boundary sees the bilinear surface's kink: a few may differ.
    assert close.mean() > 0.97, close.mean()
