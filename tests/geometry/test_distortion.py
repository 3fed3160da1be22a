"""Lens distortion of PinholeCamera: forward model and ray inversion, with OpenCV as the oracle."""

import cv2
import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, ShapeError
from torchslam.geometry import (
    PinholeCamera,
    backproject_depth,
    distort_normalized,
    distort_planes_with_jacobian,
    undistort_pixels,
    undistorted_rays,
)

FR1 = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
FR2 = PinholeCamera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172))
RATIONAL = PinholeCamera(60.0, 58.0, 31.2, 23.9, 64, 48, (0.1, -0.05, 0.002, -0.001, 0.01, 0.02, -0.01, 0.005))


def _K(cam):
    return np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])


def _cv_project(xy, cam):
    """Pixels of normalised points (N, 2) at z = 1 through OpenCV's projectPoints."""
    P = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), _K(cam), np.asarray(cam.distortion or (), dtype=np.float64))
    return uv.reshape(-1, 2)


def _grid(cam):
    v, u = np.meshgrid(np.arange(cam.height, dtype=np.float64), np.arange(cam.width, dtype=np.float64), indexing="ij")
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("cam", [FR1, FR2, RATIONAL], ids=["fr1", "fr2", "rational8"])
def test_distort_normalized_matches_opencv(cam):
    xy = (torch.rand(500, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5) * 1.2
    d = distort_normalized(xy, cam.distortion)
    pix = d * torch.tensor([cam.fx, cam.fy], dtype=torch.float64) + torch.tensor([cam.cx, cam.cy], dtype=torch.float64)
    np.testing.assert_allclose(pix.numpy(), _cv_project(xy.numpy(), cam), atol=1e-9, rtol=0)
    assert distort_normalized(xy, None) is xy


@pytest.mark.parametrize("cam", [FR1, FR2, RATIONAL], ids=["fr1", "fr2", "rational8"])
def test_undistorted_rays_redistort_to_the_pixel_grid(cam):
    rays = undistorted_rays(cam)
    assert rays.shape == (cam.width * cam.height, 2) and rays.dtype == torch.float64
    err = np.abs(_cv_project(rays.numpy(), cam) - _grid(cam)).max()
    assert err < 1e-4, err
    # The rays really differ from the pinhole ones towards the corners (fr1: ~ 10 px).
    pinhole = undistorted_rays(PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height))
    assert float(((rays - pinhole) * cam.fx).abs().max()) > 0.1
    assert undistorted_rays(cam, torch.float32).dtype == torch.float32


def test_rays_without_distortion_are_the_pinhole_factors_bit_for_bit():
    for dist in (None, (), (0.0, 0.0, 0.0, 0.0, 0.0)):
        cam = PinholeCamera(30.0, 31.0, 15.2, 11.7, 32, 24, dist)
        assert not cam.has_distortion
        for dtype in (torch.float32, torch.float64):
            rays = undistorted_rays(cam, dtype)
            depth = torch.ones(1, 1, 24, 32, dtype=dtype)
            ref, _ = backproject_depth(depth, cam.as_tensor(dtype))
            assert torch.equal(rays, ref[0, :, :2])


def test_backproject_depth_along_rays_reprojects_through_the_lens():
    cam = PinholeCamera(60.0, 58.0, 31.2, 23.9, 64, 48, (0.25, -0.9, -0.005, 0.003, 1.1))
    g = torch.Generator().manual_seed(4)
    depth = 0.5 + 3 * torch.rand(2, 1, 48, 64, generator=g, dtype=torch.float64)
    depth[1, 0, 2, 3] = 0.0
    rays = undistorted_rays(cam)
    points, valid = backproject_depth(depth, cam.as_tensor(torch.float64), rays=rays)
    assert not valid[1, 2 * 64 + 3] and int(valid.sum()) == 2 * 48 * 64 - 1
    torch.testing.assert_close(points[..., 2][valid], depth.flatten(1)[valid], atol=0, rtol=0)
    for b in range(2):
        P = points[b].numpy()[valid[b].numpy()]
        uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), _K(cam), np.asarray(cam.distortion))
        np.testing.assert_allclose(uv.reshape(-1, 2), _grid(cam)[valid[b].numpy()], atol=1e-4, rtol=0)
    # Batched rays give the same; without rays the ideal pinhole path is unchanged.
    same, _ = backproject_depth(depth, cam.as_tensor(torch.float64), rays=rays.expand(2, -1, -1))
    assert torch.equal(same, points)
    plain, _ = backproject_depth(depth, cam.as_tensor(torch.float64))
    assert not torch.allclose(plain, points)
    with pytest.raises(ShapeError, match="rays"):
        backproject_depth(depth, cam.as_tensor(torch.float64), rays=rays[:-1])
    with pytest.raises(ShapeError, match="rays"):
        backproject_depth(depth, cam.as_tensor(torch.float64), rays=rays.expand(3, -1, -1))


def test_camera_distortion_validation_and_scaling():
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, [0.1, -0.2, 0.0, 0.0, 0.3])
    assert cam.distortion == (0.1, -0.2, 0.0, 0.0, 0.3) and cam.has_distortion
    assert hash(cam) == hash(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, (0.1, -0.2, 0.0, 0.0, 0.3)))
    half = cam.scaled(0.5)
    assert half.distortion == cam.distortion and (half.width, half.fx) == (320, 250.0)
    assert PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480).distortion is None
    for bad in ((0.1,), (0.1, 0.2), (0.1, 0.2, 0.3), (0.0,) * 6, (0.0,) * 9):
        with pytest.raises(ShapeError, match="0, 4, 5 or 8 coefficients"):
            PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, bad)
    with pytest.raises(ConfigError, match="finite"):
        PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, (0.1, float("nan"), 0.0, 0.0))
    with pytest.raises(ConfigError, match="sequence of numbers"):
        PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, ("a", 0.0, 0.0, 0.0))


def test_uninvertible_distortion_raises():
    # k1 strongly negative folds the image over before its corners: no ray reaches them.
    cam = PinholeCamera(100.0, 100.0, 320.0, 240.0, 640, 480, (-2.0, 0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="cannot be inverted"):
        undistorted_rays(cam)


def test_undistorted_rays_with_a_step_are_the_strided_full_rays_and_cached():
    from torchslam.geometry import PinholeCamera, undistorted_rays
    from torchslam.geometry import camera as camera_module

    cam = PinholeCamera(129.3, 129.1, 79.6, 63.8, 161, 121, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    full = undistorted_rays(cam).view(121, 161, 2)
    for step in (2, 3):
        part = undistorted_rays(cam, step=step)
        assert torch.equal(part, full[::step, ::step].reshape(-1, 2))
    plain = PinholeCamera(129.3, 129.1, 79.6, 63.8, 161, 121)
    assert torch.equal(undistorted_rays(plain, step=2), undistorted_rays(plain).view(121, 161, 2)[::2, ::2].reshape(-1, 2))
    # Cached per (camera, step): a second call does not invert again, and callers get a copy.
    again = undistorted_rays(cam, step=2)
    again.zero_()
    assert (cam, 2) in camera_module._RAYS_CACHE
    assert torch.equal(undistorted_rays(cam, step=2), full[::2, ::2].reshape(-1, 2))
    with pytest.raises(ConfigError, match="step"):
        undistorted_rays(cam, step=0)


def test_undistort_pixels_host_path_matches_torch_bit_for_bit(monkeypatch):
    """The NumPy Newton steps on the host (in chunks) repeat the torch steps' arithmetic: the
    same rays to the last bit, for 5- and 8-coefficient models, across a chunk boundary."""
    import torchslam.geometry.camera as camera_module

    g = torch.Generator().manual_seed(3)
    for d in ((0.2624, -0.9531, -0.0054, 0.0026, 1.1633), (0.1, -0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005)):
        cam = PinholeCamera(520.0, 516.0, 320.0, 240.0, 640, 480, distortion=d)
        uv = torch.rand(camera_module._NEWTON_CHUNK + 1000, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0], dtype=torch.float64)
        for steps in (1, 4):  # one step shows the Jacobian's rounding; after several, the fixed point
            host = undistort_pixels(uv, cam, newton_steps=steps)
            with monkeypatch.context() as m:
                m.setattr(camera_module, "numpy_viewable", lambda x: False)
                dev = undistort_pixels(uv, cam, newton_steps=steps)
            assert torch.equal(host, dev), steps
        # From a start far off, where the Jacobian's rounding shows in every step.
        xd = torch.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy], -1)
        start = xd + 0.01 * torch.randn(xd.shape, generator=g, dtype=torch.float64)
        x, y = camera_module._newton_numpy(start[:, 0].numpy().copy(), start[:, 1].numpy().copy(), xd.numpy(), d, 2)
        assert torch.equal(torch.from_numpy(np.stack([x, y], -1)), camera_module._newton_torch(start, xd, d, 2))


@pytest.mark.parametrize("cam", [FR1, FR2, RATIONAL], ids=["fr1", "fr2", "rational8"])
@pytest.mark.parametrize("kind", ["tensor", "array"])
def test_distortion_with_its_jacobian_equals_the_model_and_central_differences(cam, kind):
    """The fused model and derivative: the forward model to round-off, the derivative against
    central differences of ``distort_normalized`` (float64)."""
    xy = (torch.rand(400, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) - 0.5) * 1.2
    x, y = (xy[:, 0], xy[:, 1]) if kind == "tensor" else (xy[:, 0].numpy(), xy[:, 1].numpy())
    xd, yd, j00, j01, j10, j11 = (torch.as_tensor(a) for a in distort_planes_with_jacobian(x, y, cam.distortion))
    ref = distort_normalized(xy, cam.distortion)
    torch.testing.assert_close(torch.stack([xd, yd], -1), ref, rtol=0, atol=1e-14)
    h = 1e-6
    for k, (da, db) in enumerate(((j00, j10), (j01, j11))):
        e = torch.zeros(2, dtype=torch.float64)
        e[k] = h
        num = (distort_normalized(xy + e, cam.distortion) - distort_normalized(xy - e, cam.distortion)) / (2 * h)
        torch.testing.assert_close(da, num[:, 0], rtol=0, atol=1e-7)
        torch.testing.assert_close(db, num[:, 1], rtol=0, atol=1e-7)
