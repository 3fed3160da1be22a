import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, ShapeError, check_shape
from torchslam.geometry import (
    PinholeCamera,
    backproject_depth,
    intrinsics_matrix,
    project_points,
    scale_intrinsics,
    se3_act,
    se3_exp,
    umeyama_alignment,
)

from tests._helpers import seeded


def test_backproject_then_project_is_identity_on_valid_pixels():
    cam = PinholeCamera(517.3, 516.5, 318.6, 255.3, 64, 48)
    g = seeded(0)
    depth = torch.rand(2, 1, 48, 64, generator=g, dtype=torch.float64) * 4 + 0.5
    depth[0, 0, 3, 5] = 0.0
    depth[1, 0, 7, 9] = float("nan")
    intr = cam.as_tensor(torch.float64)
    points, valid = backproject_depth(depth, intr)
    assert points.shape == (2, 48 * 64, 3) and valid.shape == (2, 48 * 64)
    assert not valid[0, 3 * 64 + 5] and not valid[1, 7 * 64 + 9] and valid.sum() == 2 * 48 * 64 - 2
    assert torch.isfinite(points).all()
    uv, in_front = project_points(points, intr.expand(2, 4))
    v, u = torch.meshgrid(torch.arange(48.0, dtype=torch.float64), torch.arange(64.0, dtype=torch.float64), indexing="ij")
    grid = torch.stack([u.reshape(-1), v.reshape(-1)], -1).expand(2, -1, -1)
    torch.testing.assert_close(uv[valid], grid[valid], atol=1e-9, rtol=0)
    assert (in_front == valid).all()


def test_intrinsics_matrix_projects_like_project_points():
    intr = torch.tensor([500.0, 490.0, 320.0, 240.0], dtype=torch.float64)
    p = torch.tensor([[0.3, -0.2, 2.0]], dtype=torch.float64)
    uvw = (intrinsics_matrix(intr) @ p.T).T
    uv, _ = project_points(p, intr)
    torch.testing.assert_close(uv, uvw[:, :2] / uvw[:, 2:], atol=1e-12, rtol=0)


def test_pyramid_scaling_keeps_pixel_centres_consistent():
    cam = PinholeCamera(520.0, 520.0, 319.5, 239.5, 640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    # The image centre stays the image centre.
    assert half.cx == pytest.approx(159.5) and half.cy == pytest.approx(119.5)
    torch.testing.assert_close(
        scale_intrinsics(cam.as_tensor(torch.float64), 0.5), half.as_tensor(torch.float64), atol=1e-12, rtol=0
    )
    with pytest.raises(ConfigError, match="focal lengths"):
        PinholeCamera(0.0, 1.0, 0.0, 0.0, 10, 10)


def _numpy_umeyama(src, dst, with_scale):
    # Independent reference (Umeyama 1991, Eqs. 34-42), written out with NumPy.
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    c = np.trace(np.diag(D) @ S) / (xs**2).sum(1).mean() if with_scale else 1.0
    return R, mu_d - c * R @ mu_s, c


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_planted_and_numpy_reference(with_scale):
    g = seeded(1)
    T = se3_exp(torch.randn(4, 6, generator=g, dtype=torch.float64))
    src = torch.randn(4, 30, 3, generator=g, dtype=torch.float64)
    s_true = torch.tensor([1.0, 2.0, 0.5, 1.3], dtype=torch.float64) if with_scale else torch.ones(4, dtype=torch.float64)
    dst = se3_act(T, src * s_true[:, None, None])
    T_est, s_est = umeyama_alignment(src, dst, with_scale=with_scale)
    torch.testing.assert_close(T_est[:, :3, :3], T[:, :3, :3], atol=1e-10, rtol=0)
    torch.testing.assert_close(s_est, s_true, atol=1e-10, rtol=0)
    noisy = dst + 0.01 * torch.randn(dst.shape, generator=g, dtype=torch.float64)
    T_n, s_n = umeyama_alignment(src, noisy, with_scale=with_scale)
    for b in range(4):
        R, t, c = _numpy_umeyama(src[b].numpy(), noisy[b].numpy(), with_scale)
        np.testing.assert_allclose(T_n[b, :3, :3].numpy(), R, atol=1e-10)
        np.testing.assert_allclose(T_n[b, :3, 3].numpy(), t, atol=1e-10)
        assert s_n[b].item() == pytest.approx(c, abs=1e-10)


def test_umeyama_weights_and_padding_and_reflection():
    g = seeded(2)
    T = se3_exp(torch.randn(1, 6, generator=g, dtype=torch.float64))
    src = torch.randn(1, 20, 3, generator=g, dtype=torch.float64)
    dst = se3_act(T, src)
    dst[0, 15:] += 5.0  # outliers with zero weight are ignored
    w = torch.ones(1, 20, dtype=torch.float64)
    w[0, 15:] = 0
    T_est, _ = umeyama_alignment(src, dst, w)
    torch.testing.assert_close(T_est, T, atol=1e-10, rtol=0)
    # A mirrored point set must still give a proper rotation.
    mirrored = src * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    T_m, _ = umeyama_alignment(src, mirrored)
    assert torch.linalg.det(T_m[0, :3, :3]).item() == pytest.approx(1.0, abs=1e-12)


def test_check_shape_binds_dims_across_arguments():
    dims = {}
    check_shape(torch.zeros(2, 5, 3), "B N 3", "a", dims)
    with pytest.raises(ShapeError, match=r"b: expected \(B, N\) with N=5, got \(2, 4\)"):
        check_shape(torch.zeros(2, 4), "B N", "b", dims)
    with pytest.raises(ShapeError, match="expected a tensor"):
        check_shape([1, 2, 3], "N", "c")
