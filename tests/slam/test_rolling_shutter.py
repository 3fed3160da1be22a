"""Rolling shutters: planted in synthetic sequences, undone by GC-SLAM's dense front-end (``readout_time``)."""

import math

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.geometry import se3_exp, se3_from_Rt, se3_inverse, se3_log, undistorted_rays
from torchslam.registration import dense as dense_module
from torchslam.registration.dense import DenseConfig, dense_images, prepare_dense_frame, register_dense_frames
from torchslam.registration.depth_align import refine_with_depth, sample_depth_points
from torchslam.registration.rolling import (
    check_readout, correct_points, correct_rows, dense_frame_at_stamp, dense_images_at_stamp, features_at_stamp, row_offsets,
)
from torchslam.registration.sparse import frame_features
from torchslam.systems.base import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig

_SMALL = dict(width=320, height=240, depth_noise=False)


def _twist(seq, k: int) -> torch.Tensor:
    """(6,) the true body twist per second at frame ``k`` (central difference of the trajectory)."""
    h = 1e-3
    t = seq.timestamps[k : k + 1]
    R0, p0 = seq._pose(t - h)
    R1, p1 = seq._pose(t + h)
    return se3_log(se3_inverse(se3_from_Rt(R0, p0)) @ se3_from_Rt(R1, p1))[0] / (2 * h)


def test_row_offsets_put_the_stamp_at_the_middle_row_and_span_the_readout():
    d = row_offsets(480, 480, 0.03)
    assert float(d[0]) == pytest.approx(-0.03 * 239.5 / 480) and float(d[-1]) == pytest.approx(0.03 * 239.5 / 480)
    assert float(d[1] - d[0]) == pytest.approx(0.03 / 480)
    # A level reduced by 2: its row r covers sensor rows 2r and 2r + 1.
    half = row_offsets(240, 480, 0.03)
    assert torch.allclose(half, (d[0::2] + d[1::2]) / 2, atol=1e-15)


def test_planted_rolling_shutter_renders_each_band_at_its_instant_and_nothing_else_moves():
    cfg = dict(frames=4, seed=2, **_SMALL)
    base, rolled = generate_sequence(SyntheticConfig(**cfg)), generate_sequence(SyntheticConfig(readout_time=0.03, **cfg))
    assert torch.equal(base.groundtruth.T_wc, rolled.groundtruth.T_wc)
    rgb, depth = rolled.render(range(4))
    rgb0, _ = base.render(range(4))
    assert not torch.allclose(rgb, rgb0, atol=1e-3)
    for r0, r1, delta, _ in (rolled._bands[0], rolled._bands[7], rolled._bands[-1]):
        R, p = rolled._pose(rolled.timestamps[:4] + delta)
        full = rolled.renderer.render(se3_from_Rt(R, p))
        assert torch.equal(full.rgb[:, :, r0:r1], rgb[:, :, r0:r1])
        assert torch.allclose(full.depth[:, :, r0:r1], depth[:, :, r0:r1], atol=2e-4)  # the depth's quantisation
    assert rolled._bands[0][2] == pytest.approx(0.03 * (7.5 - 119.5) / 240)


def test_moved_points_match_the_exact_rigid_motion_and_leave_invalid_ones():
    g = torch.Generator().manual_seed(0)
    B, h, w, H = 2, 6, 5, 480
    points = torch.rand(B, h * w, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 2.0, 3.0]) + torch.tensor([-1.0, -1.0, 0.5])
    valid = torch.rand(B, h * w, generator=g) > 0.2
    twist = torch.tensor([[0.4, -0.2, 0.3, 0.6, -0.5, 0.3], [-0.3, 0.1, 0.0, -0.2, 0.7, 0.1]], dtype=torch.float64)
    out = correct_points(points, valid, twist, w, H, 0.03)
    delta = row_offsets(h, H, 0.03).repeat_interleave(w)  # (N,)
    # Exact: X = exp(delta xi) X_row, per point.
    T = se3_exp(delta[None, :, None] * twist[:, None, :])  # (B, N, 4, 4)
    exact = (T[..., :3, :3] @ points[..., None])[..., 0] + T[..., :3, 3]
    err = (out - exact).norm(dim=-1)[valid]
    move = (exact - points).norm(dim=-1)[valid]
    # What is left is second order in delta |xi| (at most 0.015 * 0.9 here): about 1 % of the move.
    assert float((err / move).max()) < 0.02 and float(move.max()) > 0.01
    assert torch.equal(out[~valid], points[~valid])
    assert correct_points(points, valid, twist, w, H, 0.0) is points
    # The host path (NumPy, component by component) and the torch path (accelerators) agree.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dense_module, "HOST_FAST_PATHS", False)
        on_torch = correct_points(points, valid, twist, w, H, 0.03)
        on_torch32 = correct_points(points.float(), valid, twist.float(), w, H, 0.03)
    torch.testing.assert_close(out, on_torch, rtol=0, atol=1e-12)
    torch.testing.assert_close(correct_points(points.float(), valid, twist.float(), w, H, 0.03), on_torch32, rtol=0, atol=1e-6)


def test_points_at_given_rows_move_as_the_pixel_grid_does_and_orb_points_by_their_keypoint_rows():
    g = torch.Generator().manual_seed(1)
    B, h, w = 2, 8, 5
    points = torch.rand(B, h * w, 3, generator=g, dtype=torch.float64) + torch.tensor([-0.5, -0.5, 1.0])
    valid = torch.rand(B, h * w, generator=g) > 0.3
    twist = torch.randn(B, 6, generator=g, dtype=torch.float64)
    rows = torch.arange(h, dtype=torch.float64).repeat_interleave(w).expand(B, -1)
    # Full-resolution pixel rows: the same move as correct_points' (its host path, float64).
    torch.testing.assert_close(correct_rows(points, rows, valid, twist, h, 0.03), correct_points(points, valid, twist, w, h, 0.03),
                               rtol=0, atol=1e-12)
    assert correct_rows(points, rows, valid, twist, h, 0.0) is points
    with pytest.raises(ConfigError, match="readout"):
        correct_rows(points, rows, valid, twist, h, -1.0)
    # ORB features: each point by its keypoint's (sub-pixel) row; keypoints, descriptors and validity kept.
    seq = generate_sequence(SyntheticConfig(frames=1, seed=3, **_SMALL))
    f = frame_features(seq[0].rgb, seq[0].depth, seq.camera)
    tw = twist[0]
    moved = features_at_stamp(f, tw, seq.camera.height, 0.03)
    assert moved.keypoints is f.keypoints and moved.descriptors is f.descriptors and moved.valid is f.valid
    expect = correct_rows(f.points[None], f.keypoints[None, :, 1], f.valid[None], tw[None], seq.camera.height, 0.03)[0]
    torch.testing.assert_close(moved.points, expect, rtol=0, atol=0)
    assert torch.equal(moved.points[~f.valid], f.points[~f.valid])
    away = f.valid & ((f.keypoints[:, 1] - (seq.camera.height - 1) / 2).abs() > 20)
    assert int(away.sum()) > 20 and float((moved.points - f.points)[away].norm(dim=-1).min()) > 0  # rows off the middle move
    assert features_at_stamp(f, tw, seq.camera.height, 0.0) is f


def test_depth_refinement_against_a_rolling_shutter_keyframe_lands_closer_with_its_motion():
    """A keyframe's depth read with a planted 30 ms rolling shutter, a frame's depth samples at
    its stamp (a global-shutter twin): refined from the true pose, the refinement that knows the
    keyframe's motion stays near the truth, the one that does not drifts; host and torch paths agree."""
    import torchslam.registration.depth_align as module

    cfg = dict(frames=16, seed=4, trajectory="handheld", **_SMALL)
    rolled, glob = generate_sequence(SyntheticConfig(readout_time=0.03, **cfg)), generate_sequence(SyntheticConfig(**cfg))
    cam = rolled.camera
    i, j = 6, 10
    T_ij = se3_inverse(rolled.groundtruth.T_wc[i].to(torch.float64)) @ rolled.groundtruth.T_wc[j].to(torch.float64)
    pts = sample_depth_points(glob[j].depth, undistorted_rays(cam), 3000, 0.1, 10.0)
    no_orb = torch.zeros(0, 3, dtype=torch.float64)
    args = (T_ij, rolled[i].depth, cam, pts, no_orb, no_orb, torch.zeros(0, dtype=torch.bool), 4)
    tw = _twist(rolled, i)

    def error(T):
        return float((se3_inverse(T_ij) @ T)[:3, 3].norm())

    plain, _ = refine_with_depth(*args)
    known, used = refine_with_depth(*args, twist_i=tw, readout=0.03)
    assert used > 1000
    assert error(known) < 0.4 * error(plain), (error(known), error(plain))
    assert torch.equal(refine_with_depth(*args, twist_i=tw, readout=0.0)[0], plain)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(module, "numpy_viewable", lambda x: False)
        on_torch, used_torch = refine_with_depth(*args, twist_i=tw, readout=0.03)
    torch.testing.assert_close(on_torch, known, rtol=0, atol=1e-10)
    assert used_torch == used


def test_resampled_keyframe_images_come_close_to_a_global_shutter_render():
    cfg = dict(frames=12, seed=1, **_SMALL)
    rolled, glob = generate_sequence(SyntheticConfig(readout_time=0.03, **cfg)), generate_sequence(SyntheticConfig(**cfg))
    dc = DenseConfig()
    k = 9
    a, b = rolled[k], glob[k]
    rs = dense_images(a.rgb[None], a.depth[None], rolled.camera, dc)
    gs = dense_images(b.rgb[None], b.depth[None], rolled.camera, dc)
    at = dense_images_at_stamp(rs, _twist(rolled, k).float(), 0.03)
    m = (gs.depth > 0) & (at.depth > 0) & (rs.depth > 0)
    dz_rs, dz_at = ((rs.depth - gs.depth)[m]).abs().median(), ((at.depth - gs.depth)[m]).abs().median()
    dg_rs, dg_at = ((rs.grey - gs.grey)[m]).abs().mean(), ((at.grey - gs.grey)[m]).abs().mean()
    assert float(dz_at) < 0.2 * float(dz_rs)
    assert float(dg_at) < 0.35 * float(dg_rs)
    assert dense_images_at_stamp(rs, _twist(rolled, k).float(), 0.0) is rs


def test_registration_of_rolling_shutter_frames_moved_to_their_stamps_is_closer_to_the_truth():
    cfg = dict(frames=30, seed=1, **_SMALL)
    seq = generate_sequence(SyntheticConfig(readout_time=0.03, **cfg))
    dc = DenseConfig()
    err = {"as read": 0.0, "at stamps": 0.0}
    for i in (5, 15, 25):
        j = i + 3
        T_ij = se3_inverse(seq.groundtruth.T_wc[i]) @ seq.groundtruth.T_wc[j]
        a, b = seq[i], seq[j]
        A = prepare_dense_frame(a.rgb[None], a.depth[None], seq.camera, dc)
        Bf = prepare_dense_frame(b.rgb[None], b.depth[None], seq.camera, dc)
        for name in err:
            Ai, Bj = A, Bf
            if name == "at stamps":
                Ai = dense_images_at_stamp(A.images(), _twist(seq, i).float(), 0.03).pyramid()
                Bj = dense_frame_at_stamp(Bf, _twist(seq, j).float(), 0.03)
            res = register_dense_frames(Ai, Bj, torch.eye(4, dtype=torch.float64)[None], dc)
            err[name] += float((se3_inverse(T_ij) @ res.T_ij[0].to(torch.float64))[:3, 3].norm())
    assert err["at stamps"] < 0.6 * err["as read"], err


@pytest.mark.parametrize("value", [-0.01, 0.2, math.nan])
def test_a_bad_readout_is_refused_by_name(value):
    with pytest.raises(ConfigError, match="readout_time"):
        config_from_dict(GCSlamConfig, {"frontend": "dense", "readout_time": value})
    with pytest.raises(ConfigError, match="readout_time"):
        SyntheticConfig(readout_time=value)
    with pytest.raises(ConfigError, match="readout_time"):
        check_readout(value)
    with pytest.raises(ConfigError, match="readout: expected seconds"):
        correct_points(torch.zeros(1, 4, 3), torch.ones(1, 4, dtype=torch.bool), torch.zeros(1, 6), 2, 480, value)


def test_gcslam_sparse_moves_orb_points_of_frames_and_keyframes():
    seq = generate_sequence(SyntheticConfig(frames=24, seed=1, readout_time=0.03, **_SMALL))
    base = {"frontend": "sparse", "threaded": False, "prepare_ahead": False}
    system = GCSlam(config_from_dict(GCSlamConfig, {**base, "readout_time": 0.03}))
    sent = []
    system.start(seq)
    submit = system._worker.submit
    system._worker.submit = lambda ev: (sent.append(ev), submit(ev))[1]
    for k in range(len(seq)):
        system.track(seq[k])
    out = system.finish()
    rs = out.metrics["rolling_shutter"]
    assert (rs["setting"], rs["readout_time_s"], rs["source"]) == (0.03, 0.03, "readout_time")
    assert rs["keyframes"] == len(system.keyframes) >= 2 and all(k.at_stamp and k.twist is not None for k in system.keyframes)
    assert rs["frames"] == len(seq) - 2  # the first (a keyframe) and the one tracked against it as read
    # What the optimiser gets (loops, MILD) is the keyframe's moved ORB points, keypoints as read.
    for ev in sent:
        kf = system.keyframes[ev.kf]
        raw = frame_features(seq[kf.frame_index].rgb, seq[kf.frame_index].depth, seq.camera)
        assert torch.equal(ev.features.keypoints, raw.keypoints) and ev.features.points is kf.features.points
        assert float((ev.features.points - raw.points)[raw.valid].norm(dim=-1).max()) > 1e-4
        # Its dense pairs' images go as read with their motion; the optimiser resamples them.
        assert ev.images is not None and ev.images_motion is not None and ev.images_motion[1] == 0.03
        stored = system.optimizer.images[ev.kf]
        assert torch.equal(stored.depth, dense_images_at_stamp(ev.images, ev.images_motion[0].float(), 0.03).depth)
        assert float((stored.depth - ev.images.depth).abs().max()) > 1e-4
    # auto (the default) takes the planted readout with the sparse front-end too.
    auto = run_sequence(GCSlam(config_from_dict(GCSlamConfig, base)), seq).output
    assert auto.metrics["rolling_shutter"] == {**rs, "setting": "auto", "source": "synthetic"}
    torch.testing.assert_close(auto.T_wc, out.T_wc, rtol=0, atol=1e-9)
    off = run_sequence(GCSlam(config_from_dict(GCSlamConfig, {**base, "readout_time": 0})), seq).output
    assert off.metrics["rolling_shutter"]["frames"] == off.metrics["rolling_shutter"]["keyframes"] == 0


def test_gcslam_dense_moves_frames_and_keyframes_and_reports_them():
    seq = generate_sequence(SyntheticConfig(frames=24, seed=1, readout_time=0.03, **_SMALL))
    cfg = config_from_dict(GCSlamConfig, {"frontend": "dense", "threaded": False, "prepare_ahead": False, "readout_time": 0.03})
    system = GCSlam(cfg)
    out = run_sequence(system, seq).output
    rs = out.metrics["rolling_shutter"]
    assert rs["readout_time_s"] == 0.03
    # Every keyframe is moved: the first, made with no motion yet, with the motion of the first
    # frame tracked against it (which stays as read; every later frame is moved).
    assert rs["keyframes"] == len(system.keyframes) >= 2 and all(k.at_stamp for k in system.keyframes)
    assert rs["frames"] == len(seq) - 2
    assert (rs["setting"], rs["source"]) == (0.03, "readout_time")
    off = GCSlam(config_from_dict(GCSlamConfig, {"frontend": "dense", "threaded": False, "prepare_ahead": False, "readout_time": 0}))
    assert run_sequence(off, seq).output.metrics["rolling_shutter"] == {
        "setting": 0.0, "readout_time_s": 0.0, "source": "readout_time", "frames": 0, "keyframes": 0}
    # auto (the default) takes the sequence's planted readout: the same run as 0.03 set by hand.
    auto = GCSlam(config_from_dict(GCSlamConfig, {"frontend": "dense", "threaded": False, "prepare_ahead": False}))
    out_auto = run_sequence(auto, seq).output
    assert out_auto.metrics["rolling_shutter"] == {**rs, "setting": "auto", "source": "synthetic"}
    torch.testing.assert_close(out_auto.T_wc, out.T_wc, rtol=0, atol=1e-9)


def test_auto_takes_the_sequence_readout_with_either_front_end():
    dense, sparse = GCSlamConfig(frontend="dense"), GCSlamConfig()
    assert dense.readout_time == sparse.readout_time == "auto"
    planted = generate_sequence(SyntheticConfig(frames=4, readout_time=0.02, **_SMALL))
    plain = generate_sequence(SyntheticConfig(frames=4, **_SMALL))
    assert dense.readout_for(planted) == sparse.readout_for(planted) == (0.02, "synthetic")
    assert dense.readout_for(plain) == sparse.readout_for(plain) == (0.0, None)
    assert GCSlamConfig(readout_time=0.03).readout_for(plain) == (0.03, "readout_time")
    assert GCSlamConfig(frontend="dense", readout_time=0).readout_for(planted) == (0.0, "readout_time")
    assert GCSlamConfig(frontend="dense", readout_time=0.01).readout_for(plain) == (0.01, "readout_time")

    class Bare:  # a sequence that implements the protocol without the optional readout
        name = "bare"
    assert dense.readout_for(Bare()) == (0.0, None)
    for bad in ("fast", "Auto"):
        with pytest.raises(ConfigError, match="readout_time"):
            config_from_dict(GCSlamConfig, {"frontend": "dense", "readout_time": bad})



def test_a_keyframe_held_for_its_motion_reaches_the_optimiser_at_its_stamp_or_at_the_end():
    seq = generate_sequence(SyntheticConfig(frames=3, seed=1, readout_time=0.03, **_SMALL))
    cfg = config_from_dict(GCSlamConfig, {"frontend": "dense", "threaded": False, "prepare_ahead": False})
    received = []

    def run(n):
        system = GCSlam(cfg)
        system.start(seq)
        submit = system._worker.submit
        system._worker.submit = lambda ev: (received.append(ev), submit(ev))[1]
        for k in range(n):
            system.track(seq[k])
        return system, system.finish()

    # One frame: the first keyframe never sees a motion and is handed over as read when the run ends.
    system, out = run(1)
    assert [ev.kf for ev in received] == [0] and not system.keyframes[0].at_stamp
    assert len(out.T_wc) == 1 and out.metrics["rolling_shutter"]["keyframes"] == 0
    # Two frames: the second's tracked motion resamples it before the optimiser gets it.
    received.clear()
    as_read = dense_images(seq[0].rgb[None], seq[0].depth[None], seq.camera, cfg.dense)
    system, out = run(2)
    (ev,) = [ev for ev in received if ev.kf == 0]
    assert system.keyframes[0].at_stamp and out.metrics["rolling_shutter"]["keyframes"] >= 1
    assert ev.images is not None and float((ev.images.depth - as_read.depth).abs().max()) > 1e-4
