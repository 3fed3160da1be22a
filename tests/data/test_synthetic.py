"""Synthetic RGB-D-inertial generator: exact geometry, brute-force rendering oracle, noise, IMU, I/O."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch

from torchslam.data import (
    SYNTHETIC_TRAJECTORIES,
    Sequence,
    SyntheticConfig,
    TUMSequence,
    generate_sequence,
    read_tum_trajectory,
    write_tum_folder,
)
from torchslam.config import config_from_dict, config_to_dict, load_config
from torchslam.data.synthetic import (
    SceneRenderer,
    SyntheticTrajectory,
    build_scene,
    camera_from_config,
    kinect_depth_noise,
    synthetic_kinematics,
    synthetic_trajectory,
)
from torchslam.errors import ConfigError
from torchslam.geometry import backproject_depth, project_points, se3_act, se3_from_Rt, se3_inverse, so3_log
from torchslam.imu import AttitudeStream, ImuNoise, attitude_errors, integrate_gyro

F64 = torch.float64



def _small(**kw) -> SyntheticConfig:
    base = dict(frames=12, width=160, height=120, depth_noise=False, batch_size=4)
    base.update(kw)
    return SyntheticConfig(**base)


# ------------------------------------------------------------------ configuration


@pytest.mark.parametrize(
    "key, value",
    [
        ("trajectory", "spiral"),
        ("frames", 0),
        ("width", 640.0),
        ("fps", -30.0),
        ("depth_holes", 1.5),
        ("depth_noise_k", -0.001),
        ("imu_noise", 1.7e-4),
        ("imu_rate", 0.0),
        ("fx", -500.0),
        ("max_depth", 20.0),
        ("depth_noise", "yes"),
        ("texture_density", 5000.0),
        ("exposure", -0.01),
        ("exposure_samples", 1),
    ],
)
def test_bad_config_names_the_key(key, value):
    with pytest.raises(ConfigError, match=f"SyntheticConfig.{key}"):
        SyntheticConfig(**{key: value})


def test_bad_imu_noise_names_the_key():
    with pytest.raises(ConfigError, match="ImuNoise.gyro_noise_density"):
        SyntheticConfig(imu_noise=ImuNoise(gyro_noise_density=float("nan")))


def test_flat_imu_noise_keys_are_read_into_the_nested_imu_noise():
    flat = load_config(SyntheticConfig, overrides=["gyro_noise_density=1e-3", "accel_bias_init=0.5", "frames=7"])
    nested = load_config(SyntheticConfig, overrides=["imu_noise.gyro_noise_density=1e-3", "imu_noise.accel_bias_init=0.5", "frames=7"])
    assert flat == nested
    assert flat.imu_noise == ImuNoise(gyro_noise_density=1e-3, accel_bias_init=0.5) and flat.frames == 7
    # The saved form is nested, and reads back.
    assert config_to_dict(flat)["imu_noise"]["gyro_noise_density"] == 1e-3
    assert config_from_dict(SyntheticConfig, config_to_dict(flat)) == flat
    for old in ("gyro_noise_density", "gyro_bias_walk", "accel_noise_density", "accel_bias_walk", "gyro_bias_init", "accel_bias_init"):
        cfg = config_from_dict(SyntheticConfig, {old: 0.25})
        assert getattr(cfg.imu_noise, old) == 0.25
        assert cfg.imu_noise == dataclasses.replace(ImuNoise(), **{old: 0.25})


def test_flat_imu_noise_key_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"--set: imu_noise\.gyro_bias_walk: expected a finite number >= 0, got -1\.0"):
        load_config(SyntheticConfig, overrides=["gyro_bias_walk=-1"])
    with pytest.raises(ConfigError, match="gyro_noise_density: given twice, also as imu_noise.gyro_noise_density"):
        config_from_dict(SyntheticConfig, {"gyro_noise_density": 1e-3, "imu_noise": {"gyro_noise_density": 2e-3}})
    # Other nested fields may sit beside a flat one.
    cfg = config_from_dict(SyntheticConfig, {"gyro_noise_density": 1e-3, "imu_noise": {"accel_bias_walk": 0.0}})
    assert cfg.imu_noise == ImuNoise(gyro_noise_density=1e-3, accel_bias_walk=0.0)


def test_flat_imu_noise_keys_work_on_the_command_line_config():
    from torchslam.app.run import resolve_config

    _, data, resolved = resolve_config("nislam", None, ["data.synthetic.gyro_noise_density=3e-4", "data.synthetic.trajectory=loop"])
    assert data.synthetic.imu_noise == ImuNoise(gyro_noise_density=3e-4)
    assert data.synthetic.trajectory is SyntheticTrajectory.LOOP and data.synthetic.trajectory == "loop"
    assert resolved["data"]["synthetic"]["imu_noise"]["gyro_noise_density"] == 3e-4


def test_trajectory_is_an_enum_read_from_its_name():
    for kind in SYNTHETIC_TRAJECTORIES:
        cfg = SyntheticConfig(trajectory=kind)
        assert cfg.trajectory is SyntheticTrajectory(kind) and f"{cfg.trajectory}" == kind
        assert config_to_dict(cfg)["trajectory"] == kind
    assert SyntheticConfig(trajectory="HandHeld").trajectory is SyntheticTrajectory.HANDHELD


def test_bad_trajectory_lists_valid_ones():
    with pytest.raises(ConfigError) as info:
        SyntheticConfig(trajectory="spiral")
    for kind in SYNTHETIC_TRAJECTORIES:
        assert repr(kind) in str(info.value)


def test_default_camera_is_tum_fr1_scaled():
    cam = camera_from_config(SyntheticConfig())
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (517.3, 516.5, 318.6, 255.3, 640, 480)
    half = camera_from_config(SyntheticConfig(width=320, height=240))
    assert half.fx == pytest.approx(517.3 / 2) and half.cx == pytest.approx((318.6 + 0.5) / 2 - 0.5)
    custom = camera_from_config(SyntheticConfig(fx=400.0, cy=100.0))
    assert custom.fx == 400.0 and custom.cy == 100.0 and custom.fy == 516.5


# ------------------------------------------------------------------ geometry


def test_protocol_and_frames():
    seq = generate_sequence(_small(frames=6))
    assert isinstance(seq, Sequence)
    assert len(seq) == 6 and seq.timestamps.dtype == F64
    assert torch.allclose(seq.timestamps, torch.arange(6, dtype=F64) / 30)
    frame = seq[-1]
    assert frame.index == 5 and frame.timestamp == pytest.approx(5 / 30)
    assert frame.rgb.shape == (3, 120, 160) and frame.rgb.dtype == torch.float32
    assert frame.depth.shape == (1, 120, 160) and frame.depth.dtype == torch.float32
    assert 0 <= float(frame.rgb.min()) and float(frame.rgb.max()) <= 1
    assert torch.equal(frame.T_wc, seq.groundtruth.T_wc[5])
    assert [f.index for f in seq] == list(range(6))
    with pytest.raises(IndexError):
        seq[6]


def test_rendering_is_deterministic_and_batch_independent():
    cfg = _small(frames=6, depth_noise=True, depth_holes=0.05)
    a, b = generate_sequence(cfg), generate_sequence(cfg)
    rgb_a, depth_a = a.render(range(6))
    rgb_b, depth_b = b.render([5, 4, 3, 2, 1, 0])
    assert torch.equal(rgb_a, rgb_b.flip(0)) and torch.equal(depth_a, depth_b.flip(0))
    # Indexing renders the batch [4, 5]; frame noise must not depend on the batch.
    assert torch.equal(a[5].depth, depth_a[5]) and torch.equal(a[1].rgb, rgb_a[1])
    c = generate_sequence(SyntheticConfig(**{**cfg.__dict__, "seed": 1}))
    rgb_c, depth_c = c.render(range(6))
    assert not torch.equal(rgb_a, rgb_c)
    assert (depth_a != depth_c).float().mean() > 0.5


def test_exposure_blur_is_the_mean_of_renders_over_the_exposure():
    """Oracle: the blurred colour equals renders at the sub-instants, averaged; depth and pose stay sharp."""
    cfg = _small(frames=4, trajectory="loop", period=3.4, exposure=0.02, exposure_samples=3)
    seq, sharp = generate_sequence(cfg), generate_sequence(dataclasses.replace(cfg, exposure=0.0))
    rgb, depth = seq.render([1, 3])
    rgb0, depth0 = sharp.render([1, 3])
    assert torch.equal(depth, depth0)
    assert torch.equal(seq.groundtruth.T_wc, sharp.groundtruth.T_wc)
    pose = synthetic_trajectory(cfg)
    ref = torch.zeros_like(rgb)
    for dt in (-0.01, 0.0, 0.01):
        ref += seq.renderer.render(se3_from_Rt(*pose(seq.timestamps[[1, 3]] + dt))).rgb
    assert torch.allclose(rgb, ref / 3, atol=1e-6)
    # The middle sample is the sharp frame itself, and at this speed (8 cm per frame) blur moves the image.
    assert (rgb - rgb0).abs().mean() > 0.01
    assert torch.equal(seq[3].rgb, rgb[1])  # indexing renders (and blurs) the same


def test_exposure_of_a_still_camera_changes_nothing():
    cfg = _small(frames=2, trajectory="orbit", period=1e9, exposure=0.05, exposure_samples=4)
    rgb, _ = generate_sequence(cfg).render([0, 1])
    rgb0, _ = generate_sequence(dataclasses.replace(cfg, exposure=0.0)).render([0, 1])
    assert torch.allclose(rgb, rgb0, atol=1e-5)  # four float32 renders summed and divided


def test_renderer_chunking_does_not_change_images():
    cfg = _small()
    seq = generate_sequence(cfg)
    T = seq.groundtruth.T_wc[:5]
    one = SceneRenderer(seq.scene, seq.camera, chunk=1).render(T)
    many = SceneRenderer(seq.scene, seq.camera, chunk=4).render(T)
    # The surface seen at each pixel is the same; colour and depth to float32 round-off (a chunk
    # is one batched matmul, whose rounding may depend on the batch size and the CPU).
    assert torch.equal(one.prim, many.prim)
    torch.testing.assert_close(one.rgb, many.rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(one.depth, many.depth, rtol=1e-5, atol=1e-6)


def _brute_force(scene, cam, T_wc):
    """Float64 reference: every pixel's ray against every box by the slab test, nearest wins."""
    v, u = torch.meshgrid(torch.arange(cam.height, dtype=F64), torch.arange(cam.width, dtype=F64), indexing="ij")
    rays = torch.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, torch.ones_like(u)], -1).reshape(-1, 3)
    d_w = rays @ T_wc[:3, :3].T  # (N, 3)
    o_l = torch.einsum("kji,kj->ki", scene.R_wo, T_wc[:3, 3] - scene.centers)  # (K, 3)
    d_l = torch.einsum("kji,nj->nki", scene.R_wo, d_w)  # (N, K, 3)
    inv = 1 / d_l
    t1, t2 = (-scene.half - o_l) * inv, (scene.half - o_l) * inv
    t_near = torch.minimum(t1, t2).amax(-1)
    t_far = torch.maximum(t1, t2).amin(-1)
    t = torch.where((t_near <= t_far) & (t_near > 0), t_near, torch.full_like(t_near, math.inf))
    t[:, 0] = t_far[:, 0]  # the room is seen from inside
    depth, prim = t.min(-1)  # ray z components are 1, so the ray parameter is the depth
    return depth.reshape(cam.height, cam.width), prim.reshape(cam.height, cam.width)


@pytest.mark.parametrize("trajectory", SYNTHETIC_TRAJECTORIES)
def test_renderer_matches_brute_force_ray_casting(trajectory):
    seq = generate_sequence(_small(trajectory=trajectory, width=64, height=48, frames=150))
    cam = seq.camera
    T = seq.groundtruth.T_wc[[0, 70, 149]]
    out = seq.renderer.render(T)
    for b in range(3):
        depth, prim = _brute_force(seq.scene, cam, T[b])
        same = out.prim[b] == prim
        assert same.float().mean() > 0.99  # only silhouette pixels may differ by round-off
        assert (out.depth[b, 0][same].double() - depth[same]).abs().max() < 1e-5
        assert (out.depth[b, 0] > 0).all()  # the closed room leaves no pixel empty


@pytest.mark.parametrize("trajectory", SYNTHETIC_TRAJECTORIES)
def test_depth_points_lie_on_primitive_surfaces(trajectory):
    seq = generate_sequence(_small(trajectory=trajectory, frames=300))
    idx = [0, 100, 250]
    out = seq.renderer.render(seq.groundtruth.T_wc[idx])
    points, valid = backproject_depth(out.depth, seq.camera.as_tensor())
    points_w = se3_act(seq.groundtruth.T_wc[idx], points.double())
    for b in range(3):
        assert valid[b].all()
        dist = seq.scene.surface_distance(points_w[b], out.prim[b].reshape(-1))
        assert dist.max() < 1e-4


def test_reprojected_depth_and_colour_agree_between_frames():
    cfg = _small(width=320, height=240, frames=40, trajectory="handheld")
    seq = generate_sequence(cfg)
    i, j = 10, 25
    rgb, depth = seq.render([i, j])
    K = seq.camera.as_tensor(F64)
    points_j, valid_j = backproject_depth(depth[1:2].double(), K)
    T_ij = se3_inverse(seq.groundtruth.T_wc[i]) @ seq.groundtruth.T_wc[j]
    points_i = se3_act(T_ij, points_j[0])
    uv, front = project_points(points_i, K)
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    inside = valid_j[0] & front & (u >= 0) & (u < cfg.width) & (v >= 0) & (v < cfg.height)
    assert inside.float().mean() > 0.5  # the frames overlap
    z_seen = depth[0, 0, v[inside], u[inside]].double()
    err = (points_i[inside, 2] - z_seen).abs()
    assert err.median() < 1e-3
    assert (err < 0.01).float().mean() > 0.9  # the rest are occlusions and depth edges
    # Textures are attached to the surfaces: colours agree where the geometry does.
    consistent = err < 2e-3
    c_i = rgb[0][:, v[inside][consistent], u[inside][consistent]]
    c_j = rgb[1].reshape(3, -1)[:, inside.nonzero()[:, 0][consistent]]
    assert (c_i - c_j).abs().mean() < 0.05
    # A wrong relative pose breaks the agreement: the check can fail.
    wrong = se3_act(T_ij @ torch.tensor([[1, 0, 0, 0.05], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=F64), points_j[0])
    uv_w, _ = project_points(wrong, K)
    uw, vw = uv_w[:, 0].round().long(), uv_w[:, 1].round().long()
    ok = inside & (uw >= 0) & (uw < cfg.width) & (vw >= 0) & (vw < cfg.height)
    err_w = (wrong[ok, 2] - depth[0, 0, vw[ok], uw[ok]].double()).abs()
    assert (err_w < 0.01).float().mean() < 0.9 or err_w.median() > 1e-3


def test_colour_is_richly_textured():
    seq = generate_sequence(SyntheticConfig(frames=1))
    frame = seq[0]
    grey = (frame.rgb.permute(1, 2, 0).numpy() @ np.array([0.299, 0.587, 0.114])).astype(np.float32)
    gy, gx = np.gradient(grey)
    assert np.hypot(gx, gy).mean() > 0.02
    keypoints = cv2.ORB_create(nfeatures=5000).detect((grey * 255).round().astype(np.uint8), None)
    assert len(keypoints) >= 500


def test_scene_is_seeded():
    a, b, c = build_scene(3), build_scene(3), build_scene(4)
    assert torch.equal(a.centers, b.centers) and torch.equal(a.atlas, b.atlas)
    assert a.centers.shape != c.centers.shape or not torch.equal(a.centers, c.centers)


# ------------------------------------------------------------------ trajectories


def _dense_poses(kind: str, seconds: float = 10.0):
    cfg = SyntheticConfig(trajectory=kind)
    t = torch.arange(int(seconds * 100) + 1, dtype=F64) / 100
    R, p = synthetic_trajectory(cfg)(t)
    return t, R, p


@pytest.mark.parametrize("kind", SYNTHETIC_TRAJECTORIES)
def test_trajectories_stay_in_the_free_space(kind):
    _, R, p = _dense_poses(kind, 20.0)
    assert p[:, :2].abs().max() < 1.8 and p[:, 2].min() > 0.5 and p[:, 2].max() < 2.5
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=F64).expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[0], dtype=F64))
    step = so3_log(R[:-1].transpose(-1, -2) @ R[1:]).norm(dim=-1)
    assert step.max() < 0.02  # smooth: under 2 rad/s at 100 Hz


def test_trajectory_characters():
    _, R_loop, p_loop = _dense_poses("loop")
    assert (p_loop[-1] - p_loop[0]).norm() < 1e-9 and so3_log(R_loop[0].T @ R_loop[-1]).norm() < 1e-9
    assert (p_loop - p_loop[0]).norm(dim=-1).max() > 2.0  # it goes somewhere before returning
    _, R_tr, p_tr = _dense_poses("translate")
    path = (p_tr[1:] - p_tr[:-1]).norm(dim=-1).sum()
    turn = so3_log(R_tr[0].T @ R_tr).norm(dim=-1).max()
    assert path > 3.0 and turn < math.radians(10)
    _, R_orb, _ = _dense_poses("orbit")
    heading = torch.atan2(R_orb[:, 1, 2], R_orb[:, 0, 2])  # optical axis direction in the floor plane
    turn = torch.diff(heading)
    assert torch.atan2(turn.sin(), turn.cos()).sum().abs() > math.radians(300)  # most of a full turn
    t, R_hh, p_hh = _dense_poses("handheld")
    # Shake: fast wobble on top of the slow pan, a centimetre or so.
    smooth = torch.nn.functional.avg_pool1d(p_hh.T[None], 25, 1, 12, count_include_pad=False)[0].T
    wobble = (p_hh - smooth)[20:-20].norm(dim=-1)
    assert 1e-3 < wobble.max() < 0.05


# ------------------------------------------------------------------ depth noise


def test_kinect_noise_statistics():
    g = torch.Generator().manual_seed(0)
    z = torch.tensor([1.0, 2.0, 3.0, 4.0])[:, None, None].expand(4, 200, 200).contiguous()
    noisy = kinect_depth_noise(z, k=0.0015, holes=0.05, depth_scale=5000.0, generator=g)
    kept = noisy > 0
    assert (1 - kept.float().mean()).item() == pytest.approx(0.05, abs=0.005)
    for i, zi in enumerate((1.0, 2.0, 3.0, 4.0)):
        std = (noisy[i][kept[i]] - zi).std().item()
        assert std == pytest.approx(0.0015 * zi * zi, rel=0.04)
    steps = noisy[kept] * 5000
    assert (steps - steps.round()).abs().max() < 1e-2  # quantised to 1/5000 m
    clean = kinect_depth_noise(z, k=0.0, holes=0.0, depth_scale=0.0, generator=g)
    assert torch.equal(clean, z)
    with pytest.raises(ConfigError, match="holes"):
        kinect_depth_noise(z, holes=1.0)
    with pytest.raises(ConfigError, match="k:"):
        kinect_depth_noise(z, k=-1.0)


def test_rendered_noise_grows_with_depth_squared():
    cfg = _small(width=320, height=240, frames=1, trajectory="loop")
    clean = generate_sequence(cfg).render([0])[1][0, 0].double()
    noisy_cfg = SyntheticConfig(**{**cfg.__dict__, "depth_noise": True, "depth_noise_k": 0.0019, "depth_holes": 0.02})
    noisy = generate_sequence(noisy_cfg).render([0])[1][0, 0].double()
    kept = noisy > 0
    assert (1 - kept.double().mean()).item() == pytest.approx(0.02, abs=0.006)
    z, r = clean[kept], (noisy - clean)[kept]
    # Binned standard deviation against depth: log-log slope 2, scale k.
    edges = torch.quantile(z, torch.linspace(0, 1, 6, dtype=F64))
    mids, stds = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (z >= lo) & (z < hi)
        mids.append(z[sel].pow(2).mean().sqrt())
        stds.append(r[sel].std())
    mids, stds = torch.stack(mids), torch.stack(stds)
    slope = torch.diff(stds.log()).div(torch.diff(mids.log()))
    assert z.max() / z.min() > 1.8
    assert ((r / (0.0019 * z * z)).std().item()) == pytest.approx(1.0, rel=0.05)
    assert torch.linalg.lstsq(torch.stack([mids.log(), torch.ones_like(mids)], 1), stds.log()[:, None]).solution[0, 0] == pytest.approx(2.0, abs=0.25)
    assert slope.min() > 0


# ------------------------------------------------------------------ IMU and attitude


def test_sequence_imu_matches_the_camera_motion():
    quiet = ImuNoise(
        gyro_noise_density=0.0,
        gyro_bias_walk=0.0,
        gyro_bias_init=0.0,
        accel_noise_density=0.0,
        accel_bias_walk=0.0,
        accel_bias_init=0.0,
    )
    cfg = _small(frames=150, trajectory="orbit", imu_noise=quiet)
    seq = generate_sequence(cfg)
    imu = seq.imu
    assert imu.timestamps[0] == 0 and imu.timestamps[-1] >= seq.timestamps[-1]
    assert torch.allclose(torch.diff(imu.timestamps), torch.full((len(imu) - 1,), 1 / 200, dtype=F64))
    R = integrate_gyro(imu.timestamps, imu.gyro, seq.groundtruth.T_wc[0, :3, :3])
    R_frames, valid = AttitudeStream(imu.timestamps, R, "imu").at(seq.timestamps)
    assert valid.all()
    assert so3_log(R_frames.transpose(-1, -2) @ seq.groundtruth.T_wc[:, :3, :3]).norm(dim=-1).max() < 1e-5
    # Specific force against finite differences of the analytic positions.
    pose = synthetic_trajectory(cfg)
    t, h = imu.timestamps, 1e-3
    a_fd = (pose(t + h)[1] - 2 * pose(t)[1] + pose(t - h)[1]) / (h * h)
    R_t = pose(t)[0]
    expected = (R_t.transpose(-1, -2) @ (a_fd - seq.gravity_w)[:, :, None])[:, :, 0]
    assert (imu.accel - expected).abs().max() < 1e-4
    kin = synthetic_kinematics(cfg, t)
    assert torch.allclose(kin.omega_b, imu.gyro)


def test_sequence_attitude_is_a_bounded_ahrs():
    seq = generate_sequence(_small(frames=300, trajectory="loop"))
    assert seq.attitude.source == "imu"
    R, valid = seq.attitude.at(seq.timestamps)
    assert valid.all()
    tilt, yaw = attitude_errors(R, seq.groundtruth.T_wc[:, :3, :3])
    assert tilt.max() < math.radians(1.5) and yaw.abs().max() < math.radians(1.5)
    assert (tilt + yaw.abs()).max() > 1e-4  # a real filter, not the ground truth
    assert seq.imu_gyro_bias.shape == seq.imu.gyro.shape


# ------------------------------------------------------------------ TUM folder


def test_write_tum_folder_round_trip(tmp_path):
    cfg = _small(frames=5, width=64, height=48, depth_noise=True)
    seq = generate_sequence(cfg)
    out = write_tum_folder(seq, tmp_path / "synth")
    rgb, depth = seq.render(range(5))
    for kind in ("rgb", "depth"):
        rows = [ln.split() for ln in (out / f"{kind}.txt").read_text().splitlines() if ln and not ln.startswith("#")]
        assert len(rows) == 5
        assert [float(r[0]) for r in rows] == pytest.approx(seq.timestamps.tolist(), abs=1e-6)
        for k, (_, name) in enumerate(rows):
            img = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
            if kind == "rgb":
                assert img.dtype == np.uint8 and img.shape == (48, 64, 3)
                back = torch.from_numpy(img[:, :, ::-1].copy()).permute(2, 0, 1).float() / 255
                assert (back - rgb[k]).abs().max() <= 0.5 / 255 + 1e-6
            else:
                assert img.dtype == np.uint16 and img.shape == (48, 64)
                assert torch.allclose(torch.from_numpy(img.astype(np.float32)) / 5000, depth[k, 0], atol=1e-6)
    gt = read_tum_trajectory(out / "groundtruth.txt")
    assert torch.allclose(gt.timestamps, seq.timestamps, atol=1e-6)
    assert torch.allclose(gt.T_wc, seq.groundtruth.T_wc, atol=1e-6)
    calib = [ln.split() for ln in (out / "calibration.txt").read_text().splitlines() if not ln.startswith("#")][0]
    cam = seq.camera
    assert [float(x) for x in calib[:5]] == pytest.approx([cam.fx, cam.fy, cam.cx, cam.cy, 5000.0])
    assert [int(x) for x in calib[5:]] == [64, 48]
    imu_text = (out / "imu.txt").read_text().splitlines()
    assert imu_text[0].startswith("#") and any("timestamp gx gy gz ax ay az" in ln for ln in imu_text if ln.startswith("#"))
    imu_rows = torch.tensor([[float(x) for x in ln.split()] for ln in imu_text if not ln.startswith("#")], dtype=F64)
    assert imu_rows.shape == (len(seq.imu), 7)
    assert torch.allclose(imu_rows[:, 1:4], seq.imu.gyro, atol=1e-8)
    assert torch.allclose(imu_rows[:, 4:7], seq.imu.accel, atol=1e-8)
    # The project's TUM reader loads the folder back.
    tum = TUMSequence(out)
    assert len(tum) == 5 and tum.camera.width == 64
    frame = tum[3]
    assert torch.allclose(frame.depth, depth[3], atol=1e-6)
    assert (frame.rgb - rgb[3]).abs().max() <= 0.5 / 255 + 1e-6
