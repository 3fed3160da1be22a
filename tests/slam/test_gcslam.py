"""GC-SLAM end to end: synthetic sequences with exact ground truth, fr1/xyz, loops, bad input."""

import dataclasses

import re

import pytest
import torch

from torchslam.config import config_from_dict, config_to_dict, load_config
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data.tum import TUMSequence
from torchslam.errors import ConfigError, TorchSlamError
from torchslam.fastgo import PairStats
from torchslam.fastgo.synthetic import make_correspondences
from torchslam.geometry import se3_exp, se3_inverse, se3_log
from torchslam.systems import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.gcslam import frontend as fe
from torchslam.systems.gcslam import optimizer as go
from torchslam.systems.gcslam import system as gc
from torchslam.systems.gcslam.config import Frontend
from torchslam.systems.monitor import Monitor
from torchslam.registration.dense import dense_images
from torchslam.registration.sparse import FrameFeatures

from tests._helpers import REPO_ROOT, run_gcslam as _run

SMALL = dict(width=320, height=240)


def test_frontend_option_is_an_enum_that_takes_the_strings():
    assert GCSlamConfig(frontend="dense").frontend is Frontend.DENSE
    assert GCSlamConfig(frontend="Sparse").frontend is Frontend.SPARSE
    assert config_from_dict(GCSlamConfig, {"frontend": "dense"}) == GCSlamConfig(frontend=Frontend.DENSE)
    assert config_to_dict(GCSlamConfig(frontend="dense"))["frontend"] == "dense"
    # One front-end object per option, both with the same interface.
    assert {k: fe.frontend_class(k).kind for k in Frontend} == {k: k for k in Frontend}


def test_yaml_defaults_equal_code_defaults():
    assert load_config(GCSlamConfig, REPO_ROOT / "configs" / "gcslam.yaml") == GCSlamConfig()


@pytest.mark.parametrize("trajectory", ["translate", "orbit"])
def test_sparse_tracks_synthetic_translation_and_rotation(trajectory):
    seq = generate_sequence(SyntheticConfig(frames=60, trajectory=trajectory, seed=1, **SMALL))
    result, a = _run(seq, loops=False)
    out = result.output
    assert len(out.T_wc) == 60 and torch.isfinite(out.T_wc).all()
    assert out.metrics["tracking"]["lost_frames"] == 0
    # Every frame after the first was registered, each guided or redone by brute force.
    reg = out.metrics["registrations"]
    assert set(reg) == {"guided", "fallback", "depth_refined"} and reg["guided"] + reg["fallback"] >= 59 and reg["guided"] > 0, reg
    assert len(out.keyframe_indices) >= 2
    # Exact geometry up to Kinect-like depth noise: millimetre-level drift over 2 s.
    assert a.stats["rmse"] < 0.01, a.stats


def test_sparse_keeps_tracking_a_motion_blurred_fast_walk():
    """``orb_min_fast_threshold``: 8 cm and 3.5 degrees between frames, 20 ms exposure. The blurred
    frames keep a few dozen FAST corners at threshold 20, and the sparse front-end loses them;
    detected again at 7 every frame is tracked to millimetres."""
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="loop", period=3.4, seed=3, exposure=0.02,
                                            exposure_samples=6, **SMALL))
    lost, _ = _run(seq, loops=False, orb_min_fast_threshold=20)
    assert lost.output.metrics["tracking"]["lost_frames"] >= 5
    result, a = _run(seq, loops=False)
    assert result.output.metrics["tracking"]["lost_frames"] == 0
    assert result.output.metrics["tracking"]["tracking_failures"] == 0
    assert a.stats["rmse"] < 0.005, a.stats


def test_sparse_poses_refined_against_the_keyframe_depth_are_closer_frame_to_frame():
    """``depth_refine_points``: every registration refined; the frame-to-frame error falls (the
    ORB poses of a noisy-depth synthetic walk err by millimetres, the refined ones by less)."""
    seq = generate_sequence(SyntheticConfig(frames=40, trajectory="handheld", seed=5, **SMALL))
    rpe = {}
    for n in (0, 3000):
        result, _ = _run(seq, loops=False, depth_refine_points=n)
        out = result.output
        assert out.metrics["tracking"]["lost_frames"] == 0
        refined = out.metrics["registrations"]["depth_refined"]
        assert refined == 0 if n == 0 else refined >= 39, refined
        T_gt = torch.stack([seq[int(i)].T_wc.to(torch.float64) for i in out.frame_indices])
        rel = se3_inverse(out.T_wc[:-1]) @ out.T_wc[1:]
        rel_gt = se3_inverse(T_gt[:-1]) @ T_gt[1:]
        rpe[n] = float((se3_inverse(rel_gt) @ rel)[:, :3, 3].norm(dim=-1).pow(2).mean().sqrt())
    assert rpe[3000] < 0.8 * rpe[0], rpe


@pytest.mark.parametrize("frontend,points", [("sparse", 3000), ("sparse", 0), ("dense", 3000)])
def test_only_the_current_keyframe_keeps_its_depth_and_only_where_it_is_read(frontend, points):
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="translate", seed=1, **SMALL))
    s = GCSlam(config_from_dict(GCSlamConfig, {"frontend": frontend, "depth_refine_points": points, "threaded": False}))
    s.start(seq)
    for f in seq:
        s.track(f)
    assert len(s.keyframes) >= 2
    assert all(k.depth is None for k in s.keyframes[:-1])
    assert (s.keyframes[-1].depth is not None) == (frontend == "sparse" and points > 0)
    s.finish()


@pytest.mark.parametrize("fraction", [0.2, 0.0])
def test_sparse_guided_registration_with_few_of_the_keypoints_is_checked_by_brute_force(fraction):
    # 7.7 cm and 7.3 degrees between frames, each registration guided from the last pose (no
    # motion prior): one frame's window locks onto 72 self-consistent matches of ~1,900 keypoints,
    # which pass guided_min_inliers (50) and put it 40 cm off; guided_min_fraction sends it to
    # brute force, which keeps ~820 inliers at the right pose.
    seq = generate_sequence(SyntheticConfig(frames=14, fps=5.0, trajectory="orbit", seed=0))
    result, a = _run(seq, loops=False, motion_prior="none", sparse={"guided_min_fraction": fraction})
    if fraction:
        assert a.stats["max"] < 0.002, a.stats
    else:
        assert a.stats["max"] > 0.1, a.stats  # the failure the test guards against
        assert result.output.metrics["registrations"]["guided"] >= 1


def test_dense_tracks_synthetic_sequence():
    seq = generate_sequence(SyntheticConfig(frames=40, trajectory="translate", seed=2, **SMALL))
    result, a = _run(seq, frontend="dense", loops=False)
    assert result.output.metrics["frontend"] == "dense"
    assert result.output.metrics["tracking"]["lost_frames"] == 0
    assert a.stats["rmse"] < 0.01, a.stats


@pytest.mark.parametrize("orb_start", [True, False])
def test_dense_registration_started_far_off_is_started_again_from_orb(monkeypatch, orb_start):
    # One frame's motion prior is put 25 cm and 20 degrees off (a sudden reversal of fast
    # motion): the dense registration from there fails or keeps few correspondences, and the
    # ORB start recovers the frame's pose; without it the frame counts as a tracking failure
    # or a weak registration whose error stays.
    seq = generate_sequence(SyntheticConfig(frames=16, trajectory="translate", seed=2, **SMALL))
    original = gc.GCSlam._predicted_T_kf
    calls = {"n": 0}

    def far_off(self, t):
        T = original(self, t)
        calls["n"] += 1
        if calls["n"] == 8:
            return T @ se3_exp(torch.tensor([0.25, 0.0, 0.0, 0.0, 0.35, 0.0], dtype=T.dtype))
        return T

    monkeypatch.setattr(gc.GCSlam, "_predicted_T_kf", far_off)
    # (The residual test's starts, ``dense_orb_start_residual``, are tested on their own below.)
    result, a = _run(seq, frontend="dense", loops=False, dense_orb_start=orb_start, dense_orb_start_residual=0.0)
    tracking = result.output.metrics["tracking"]
    if orb_start:
        assert tracking["orb_starts"] == 1 and tracking["orb_starts_kept"] == 1, tracking
        assert tracking["tracking_failures"] == 0
        assert a.stats["max"] < 0.01, a.stats
    else:
        assert tracking["orb_starts"] == 0
        assert tracking["tracking_failures"] >= 1 or a.stats["max"] > 0.02, (tracking, a.stats)


@pytest.mark.parametrize("ratio", [3.0, 0.0])
def test_dense_registration_with_an_outlying_residual_is_started_again_from_orb(ratio):
    # 7.7 cm and 7.3 degrees between frames, each registration started at the last pose (no
    # motion prior): some converge to a wrong pose that keeps its correspondences, so the
    # correspondence test does not catch them; their photometric residual is ten times the
    # others', and the start from ORB finds the right pose.
    seq = generate_sequence(SyntheticConfig(frames=30, fps=5.0, trajectory="orbit", seed=0, **SMALL))
    result, a = _run(seq, frontend="dense", motion_prior="none", loops=False, dense_orb_start_residual=ratio)
    tracking = result.output.metrics["tracking"]
    if ratio:
        assert tracking["orb_starts_kept"] >= 1 and tracking["orb_starts_residual"] >= 1, tracking
        assert a.stats["rmse"] < 0.002, a.stats
    else:
        assert tracking["orb_starts_residual"] == 0
        assert a.stats["rmse"] > 0.02, a.stats  # the failure the test guards against


@pytest.mark.parametrize("check", [True, False])
def test_dense_keyframe_link_that_disagrees_with_orb_is_started_again_from_orb(monkeypatch, check):
    # One frame's dense registration is put 30 cm off with twice its photometric residual (a
    # wrong basin that keeps its correspondences, below the residual test's 3x median): the
    # displacement makes it a keyframe, whose link to the graph would carry the error. The ORB
    # registration to the keyframe disagrees with it, the dense registration started from the
    # ORB pose has the lower residual and is kept. (Without the check, the next frame's
    # prediction from the wrong pose is caught by the weak-registration test, and the optimiser's
    # keyframe pairs repair this synthetic link, so the run's error is not the signal here.)
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="translate", seed=2, **SMALL))
    original, original_track = fe.DenseFrontend.register, gc.GCSlam.track
    state = {"frame": -1, "calls": 0}

    def track(self, frame):
        state["frame"], state["calls"] = frame.index, 0
        return original_track(self, frame)

    def register(self, keyframe, frame, T_guess):
        reg = original(self, keyframe, frame, T_guess)
        state["calls"] += 1
        if state["frame"] != 16 or state["calls"] > 1:
            return reg
        off = reg.T_kf @ se3_exp(torch.tensor([0.3, 0.0, 0.0, 0.0, 0.3, 0.0], dtype=torch.float64))
        result = dataclasses.replace(reg.result, residual_photometric=reg.result.residual_photometric * 2)
        return dataclasses.replace(reg, T_kf=off, result=result)

    monkeypatch.setattr(gc.GCSlam, "track", track)
    monkeypatch.setattr(fe.DenseFrontend, "register", register)
    result, a = _run(seq, frontend="dense", loops=False, dense_orb_start_residual=0.0, dense_orb_keyframe_check=check)
    tracking = result.output.metrics["tracking"]
    assert tracking["orb_checks"] == (len(result.output.keyframe_indices) - 1 if check else 0), tracking
    if check:
        assert tracking["orb_starts_check"] == 1 and tracking["orb_starts_kept"] == 1, tracking
        assert a.stats["max"] < 0.01, a.stats
    else:
        assert tracking["orb_starts_check"] == 0


def test_inlier_shift_measures_how_far_a_pose_moves_the_orb_inliers_from_the_orb_pose():
    g = torch.Generator().manual_seed(5)
    p_j = torch.rand(1, 50, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    T = se3_exp(torch.tensor([0.1, -0.05, 0.02, 0.1, 0.0, -0.2], dtype=torch.float64))
    p_i = p_j @ T[:3, :3].T + T[:3, 3]
    inliers = torch.ones(1, 50, dtype=torch.bool)
    inliers[0, :10] = False
    p_i[0, :10] += 5.0  # outliers, left out of the mean
    res = type("S", (), {"points_i": p_i, "points_j": p_j, "inliers": inliers, "T_ij": T[None]})()
    assert gc._inlier_shift(res, T) < 1e-12
    shifted = T.clone()
    shifted[:3, 3] += torch.tensor([0.03, 0.0, 0.04], dtype=torch.float64)
    assert abs(gc._inlier_shift(res, shifted) - 0.05) < 1e-12


def test_dense_registration_to_a_fresh_keyframe_is_compared_with_the_keyframe_link():
    # Before any frame is tracked to a keyframe, a weak dense registration is judged against the
    # correspondences of the registration that linked the keyframe; afterwards against the best
    # tracked count, as before.
    system = GCSlam(GCSlamConfig(threaded=False, frontend="dense"))
    system.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    kf = type("K", (), {"dense": object()})()

    def reg(n, ok=True):
        return fe.Registration(ok, torch.eye(4, dtype=torch.float64), None, n)

    assert not system._needs_orb_start(kf, reg(10))  # nothing to compare with (the first keyframe)
    system._link_correspondences = 40000
    assert system._needs_orb_start(kf, reg(19999)) and not system._needs_orb_start(kf, reg(20001))
    assert system._needs_orb_start(kf, reg(30000, ok=False))
    system._best_correspondences = 30000
    assert not system._needs_orb_start(kf, reg(19999)) and system._needs_orb_start(kf, reg(14999))
    assert not system._needs_orb_start(type("K", (), {"dense": None})(), reg(10))  # sparse keyframe


def test_residual_outlier_test_starts_from_orb_until_it_has_a_history_then_compares_with_its_median():
    system = GCSlam(GCSlamConfig(threaded=False, frontend="dense"))
    system.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    kf = type("K", (), {"dense": object()})()

    def reg(residual, ok=True):
        result = type("R", (), {"residual_photometric": torch.tensor([residual], dtype=torch.float64)})()
        return fe.Registration(ok, torch.eye(4, dtype=torch.float64), result, 100)

    assert system._residual_outlier(kf, reg(0.001))  # no history yet: every registration is checked
    system._residuals.extend([0.02, 0.05])
    assert system._residual_outlier(kf, reg(0.001))  # still fewer than 3
    system._residuals.append(0.03)
    assert system._residual_outlier(kf, reg(0.0901))  # above 3 x the median 0.03
    assert not system._residual_outlier(kf, reg(0.0899))
    assert not system._residual_outlier(kf, reg(0.5, ok=False))  # a failure goes the other way
    assert not system._residual_outlier(type("K", (), {"dense": None})(), reg(0.5))  # sparse keyframe
    system.cfg = dataclasses.replace(system.cfg, dense_orb_start_residual=0.0)
    assert not system._residual_outlier(kf, reg(0.5))
    system.cfg = dataclasses.replace(system.cfg, dense_orb_start_residual=3.0, dense_orb_start=False)
    assert not system._residual_outlier(kf, reg(0.5))
    with pytest.raises(ConfigError, match="dense_orb_start_residual"):
        config_from_dict(GCSlamConfig, {"dense_orb_start_residual": -1})


def test_loop_closure_is_found_accepted_and_lowers_error():
    # Two MILD candidates per keyframe instead of five: the same mechanism at a third of the
    # suite's time (this fast lap makes a keyframe of every other frame).
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, **SMALL))
    few = {"mild": {"top_k": 2}}
    with_loops, a_loop = _run(seq, **few)
    without, a_none = _run(seq, loops=False)
    loops = with_loops.output.metrics["loops"]
    assert loops["accepted"] >= 1, loops
    assert with_loops.output.metrics["pairs"]["loop"] >= 1
    assert a_loop.stats["rmse"] <= a_none.stats["rmse"] + 1e-4, (a_loop.stats["rmse"], a_none.stats["rmse"])
    # Every accepted loop joins two views of the same place: close cameras looking the same way
    # (MILD proposes places by appearance; distinct places must not end up linked).
    T = torch.stack([seq[i].T_wc for i in range(len(seq))])
    closes = with_loops.output.metrics["loop_frames"]
    assert closes and any(abs(i - j) > 20 for i, j in closes)  # a revisit, not only recent neighbours
    for i, j in closes:
        dist = float((T[i, :3, 3] - T[j, :3, 3]).norm())
        cos = float((T[i, :3, 2] * T[j, :3, 2]).sum())
        assert dist < 1.0 and cos > 0.7, (i, j, dist, cos)
    # FastGO after every keyframe (the paper) instead of only before loop tests (the default):
    # each loop test optimises the whole graph, and so does the final run, so the trajectories
    # agree to round-off (8.9e-15 m when written).
    every, _ = _run(seq, fastgo_every_keyframe=True, **few)
    assert every.output.metrics["loops"] == loops
    assert torch.equal(every.output.keyframe_indices, with_loops.output.keyframe_indices)
    torch.testing.assert_close(every.output.T_wc, with_loops.output.T_wc, rtol=0, atol=1e-6)


def test_frames_between_keyframes_follow_the_corrected_link_and_keyframes_stay():
    # The sparse front-end's keyframe links are measured again densely by the optimiser, so the
    # keyframe poses differ from the tracked links even without a loop.
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="orbit", seed=1, **SMALL))
    spread, a_spread = _run(seq)
    plain, a_plain = _run(seq, spread_corrections=False)
    out, ref = spread.output, plain.output
    assert out.metrics["dense_pairs"]["odometry"] >= 2
    assert torch.equal(out.keyframe_indices, ref.keyframe_indices)
    torch.testing.assert_close(out.keyframe_T_wc, ref.keyframe_T_wc, rtol=0, atol=0)
    rows = torch.isin(out.frame_indices, out.keyframe_indices)
    torch.testing.assert_close(out.T_wc[rows], ref.T_wc[rows], rtol=0, atol=1e-12)
    moved = (out.T_wc[~rows, :3, 3] - ref.T_wc[~rows, :3, 3]).norm(dim=-1)
    assert float(moved.max()) > 1e-5 and float(moved.max()) < 0.02, moved.max()
    assert a_spread.stats["rmse"] <= a_plain.stats["rmse"] * 1.05, (a_spread.stats["rmse"], a_plain.stats["rmse"])


def test_threaded_optimisation_equals_synchronous():
    seq = generate_sequence(SyntheticConfig(frames=24, trajectory="orbit", seed=3, **SMALL))
    sync = run_sequence(GCSlam(GCSlamConfig(threaded=False)), seq).output
    thr = run_sequence(GCSlam(GCSlamConfig(threaded=True)), seq).output
    assert torch.equal(sync.keyframe_indices, thr.keyframe_indices)
    torch.testing.assert_close(thr.T_wc, sync.T_wc, rtol=0, atol=1e-12)


def _optimizer_with_route(n=8):
    """An optimiser that has taken n keyframes along a planted noise-free arc."""
    k = torch.arange(n, dtype=torch.float64)
    xi = torch.stack([0.3 * k, 0.05 * k, torch.zeros_like(k), torch.zeros_like(k), 0.1 * k, torch.zeros_like(k)], -1)
    T_gt = se3_exp(xi)
    opt = go.Optimizer(GCSlamConfig(threaded=False), Monitor())
    feats = FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3, dtype=torch.float64),
                             torch.zeros(0, dtype=torch.bool))
    pairs = torch.stack([torch.arange(n - 1), torch.arange(1, n)], -1)
    p_i, p_j = make_correspondences(T_gt, pairs, 50, 0.0, torch.Generator().manual_seed(0))
    for k in range(n):
        if k == 0:
            ev = go.KeyframeEvent(0, None, None, None, feats, None)
        else:
            stats = PairStats.from_padded(p_i[k - 1 : k], p_j[k - 1 : k])
            ev = go.KeyframeEvent(k, k - 1, se3_inverse(T_gt[k - 1]) @ T_gt[k], stats, feats, None)
        gc.insert_keyframe(opt, ev)
    return opt, T_gt


def test_planted_false_loop_is_rejected_and_true_loop_accepted(monkeypatch):
    opt, T_gt = _optimizer_with_route()
    n = len(T_gt)
    before = torch.stack(opt.T_wk).clone()
    torch.testing.assert_close(before, T_gt, rtol=0, atol=1e-9)

    def fake_registration(T_true, offset):
        def register(fi, fj, cfg, generator):
            # Correspondences that a wrong place would give: the true points of keyframe 0
            # paired with points shifted by ``offset`` in the new keyframe.
            g = torch.Generator().manual_seed(5)
            p0 = torch.rand(1, 80, 3, generator=g, dtype=torch.float64) * 2 + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            Tk0 = se3_inverse(T_true)  # frame 0 -> frame n-1
            pk = p0 @ Tk0[:3, :3].T + Tk0[:3, 3] + offset
            stats = PairStats.from_padded(p0, pk)
            return type("R", (), {"success": torch.tensor([True]), "stats": stats, "T_ij": T_true[None]})()
        return register

    T_0k = se3_inverse(T_gt[0]) @ T_gt[n - 1]
    monkeypatch.setattr(go, "register_sparse_batch", fake_registration(T_0k, torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)))
    opt.close_loops(n - 1, [0])
    assert opt.loops == {"candidates": 1, "registered": 1, "accepted": 0, "rejected": 1}
    torch.testing.assert_close(torch.stack(opt.T_wk), before, rtol=0, atol=0)
    assert "loop" not in opt.pair_kind

    monkeypatch.setattr(go, "register_sparse_batch", fake_registration(T_0k, torch.zeros(3, dtype=torch.float64)))
    opt.close_loops(n - 1, [0])
    assert opt.loops["accepted"] == 1 and opt.pair_kind.count("loop") == 1
    torch.testing.assert_close(torch.stack(opt.T_wk), T_gt, rtol=0, atol=1e-8)


@pytest.mark.parametrize("frontend,limit_m", [("sparse", 0.03), ("dense", 0.03)])
def test_tum_fr1_xyz(shared_data, frontend, limit_m):
    seq = TUMSequence(shared_data / "tum_fr1_xyz", end=100, prefetch=2)
    result, a = _run(seq, frontend=frontend)
    out = result.output
    assert len(out.T_wc) == len(seq)
    assert out.metrics["tracking"]["lost_frames"] <= 2
    assert a.stats["rmse"] < limit_m, a.stats


class _Frames:
    """A sequence made of given frames (camera and ground truth from another sequence)."""

    def __init__(self, base, frames):
        self.name, self.camera, self.groundtruth = "edited", base.camera, None
        self.frames = frames
        self.timestamps = torch.tensor([f.timestamp for f in frames], dtype=torch.float64)

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)


def test_frames_without_depth_and_unrelated_frames_do_not_crash():
    base = generate_sequence(SyntheticConfig(frames=24, trajectory="translate", seed=4, **SMALL))
    frames = [base[i] for i in range(len(base))]
    frames[5] = dataclasses.replace(frames[5], depth=torch.zeros_like(frames[5].depth))
    g = torch.Generator().manual_seed(0)
    for i in range(10, 22):  # noise images: nothing to register against
        frames[i] = dataclasses.replace(frames[i], rgb=torch.rand(frames[i].rgb.shape, generator=g))
    out = run_sequence(GCSlam(GCSlamConfig(threaded=False, max_lost=3)), _Frames(base, frames)).output
    t = out.metrics["tracking"]
    assert t["no_depth"] == 1
    assert t["lost_frames"] >= 1 and t["unlinked_keyframes"] >= 1
    assert torch.isfinite(out.T_wc).all()
    assert len(out.T_wc) == len(frames)


def test_lost_frames_are_counted_apart_from_tracked_ones(tmp_path):
    from torchslam.cli import _run_line
    from torchslam.app.outputs import write_run

    from tests._helpers import EditedSequence

    base = generate_sequence(SyntheticConfig(frames=20, trajectory="translate", seed=4, **SMALL))
    g = torch.Generator().manual_seed(0)
    noise = {i: torch.rand(base[i].rgb.shape, generator=g) for i in (8, 9, 10)}

    def plant(f):  # unrelated content: nothing to register or relocalise against
        return dataclasses.replace(f, rgb=noise[f.index]) if f.index in noise else f

    edited = EditedSequence(base, plant)
    result = run_sequence(GCSlam(GCSlamConfig(threaded=False)), edited)
    out = result.output
    t = out.metrics["tracking"]
    assert t["lost_frames"] == 3 and t["unlinked_keyframes"] == 0
    assert out.prior_indices.tolist() == [8, 9, 10]
    m = write_run(tmp_path, "gcslam", result, edited)
    assert (m["tracked_frames"], m["prior_frames"], m["posed_frames"]) == (17, 3, 20)
    assert "17/20 frames tracked, 3 on motion prior," in _run_line("gcslam", m)
    # Lost long enough to start an unlinked keyframe at the last pose: a prior too, while unlinked.
    many = {i: torch.rand(base[i].rgb.shape, generator=g) for i in range(8, 14)}
    edited = EditedSequence(base, lambda f: dataclasses.replace(f, rgb=many[f.index]) if f.index in many else f)
    out = run_sequence(GCSlam(GCSlamConfig(threaded=False, max_lost=2, loops=False)), edited).output
    t = out.metrics["tracking"]
    assert t["unlinked_keyframes"] >= 1
    assert len(out.prior_indices) == t["lost_frames"] + t["unlinked_keyframes"]


def test_bad_config_values_name_the_key():
    with pytest.raises(ConfigError, match=re.escape("frontend: 'icp' is not one of ['sparse', 'dense']")):
        GCSlamConfig(frontend="icp")
    with pytest.raises(ConfigError, match="keyframe_displacement"):
        config_from_dict(GCSlamConfig, {"keyframe_displacement": 0})
    with pytest.raises(ConfigError, match="sparse.nope"):
        config_from_dict(GCSlamConfig, {"sparse": {"nope": 1}})


@pytest.mark.parametrize("threaded", [True, False])
def test_optimiser_failure_is_reported_not_lost(monkeypatch, threaded):
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="orbit", seed=7, **SMALL))
    real = go.Optimizer.begin

    def begin(self, ev):
        if ev.kf == 2:
            raise RuntimeError("planted optimiser failure")
        return real(self, ev)

    monkeypatch.setattr(go.Optimizer, "begin", begin)
    with pytest.raises((RuntimeError, TorchSlamError), match="planted optimiser failure"):
        run_sequence(GCSlam(GCSlamConfig(threaded=threaded)), seq)


def test_keyframe_displacement_is_zero_at_the_keyframe_pose_with_lens_distortion():
    import dataclasses

    base = generate_sequence(SyntheticConfig(frames=2, trajectory="translate", seed=8, **SMALL))
    cam = dataclasses.replace(base.camera, distortion=(0.2624, -0.9531, -0.0054, 0.0026, 1.1633))

    class Distorted(_Frames):
        pass

    seq = Distorted(base, [base[0], base[1]])
    seq.camera = cam
    system = GCSlam(GCSlamConfig(threaded=False))
    system.start(seq)
    system.track(seq[0])
    kf = system.keyframes[0]
    assert system._displacement(kf, torch.eye(4, dtype=torch.float64)) < 1e-9
    # A pure 1-degree yaw moves the centre points by about f * tan(1 deg).
    T = se3_exp(torch.tensor([0, 0, 0, 0, 0.0174533, 0], dtype=torch.float64))
    moved = system._displacement(kf, T)
    assert 0.8 * cam.fx * 0.01745 < moved < 1.6 * cam.fx * 0.01745


def test_motion_prior_continues_the_last_step_and_knows_when_not_to():
    sys_ = GCSlam(GCSlamConfig(threaded=False))
    sys_.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    xi = torch.tensor([0.01, -0.02, 0.005, 0.002, 0.01, -0.003], dtype=torch.float64)
    T1 = se3_exp(xi * 0.5)  # the step from t = 0.0 to 0.5 ... scaled below
    sys_._last_T_kf, sys_._last_time = torch.eye(4, dtype=torch.float64), 0.0
    sys_._update_velocity(T1, 0.1)  # one step of 0.1 s
    sys_._last_T_kf = T1
    # 0.05 s later: half the step again, applied in the frame's own coordinates
    torch.testing.assert_close(sys_._predicted_T_kf(0.15), T1 @ se3_exp(xi * 0.25), atol=1e-12, rtol=0)
    # beyond motion_prior_max_gap (0.2 s), backwards in time, and after a lost frame: the last pose
    torch.testing.assert_close(sys_._predicted_T_kf(0.5), T1, atol=0, rtol=0)
    torch.testing.assert_close(sys_._predicted_T_kf(0.05), T1, atol=0, rtol=0)
    sys_._velocity = None
    torch.testing.assert_close(sys_._predicted_T_kf(0.15), T1, atol=0, rtol=0)
    off = GCSlam(GCSlamConfig(threaded=False, motion_prior="none"))
    off.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    off._last_T_kf, off._last_time, off._velocity = T1, 0.1, xi
    torch.testing.assert_close(off._predicted_T_kf(0.15), T1, atol=0, rtol=0)


def test_motion_prior_spans_a_gap_of_exactly_its_limit_despite_rounding():
    # A 5 Hz stream against the default 0.2 s limit: k / 5 - (k - 1) / 5 lands a few ulps either
    # side of 0.2, and the prior must hold for all of them (it was dropped for the larger ones).
    sys_ = GCSlam(GCSlamConfig(threaded=False, motion_prior_max_gap=0.2))
    sys_.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    xi = torch.tensor([0.01, -0.02, 0.005, 0.002, 0.01, -0.003], dtype=torch.float64)
    gaps = [k / 5 - (k - 1) / 5 for k in range(1, 40)]
    assert any(g > 0.2 for g in gaps)  # the case that rounding makes
    for k in range(1, 40):
        t0, t1 = (k - 1) / 5, k / 5
        sys_._last_T_kf, sys_._last_time, sys_._velocity = torch.eye(4, dtype=torch.float64), t0, None
        sys_._update_velocity(se3_exp(xi), t1)
        assert sys_._velocity is not None, (t0, t1)
        sys_._last_T_kf = se3_exp(xi)  # the tracker records the frame
        torch.testing.assert_close(sys_._predicted_T_kf(t1 + (t1 - t0)), se3_exp(xi) @ se3_exp(xi), atol=1e-9, rtol=0)
    # a gap clearly beyond the limit still drops the prior
    assert sys_._predicted_T_kf(t1 + 0.21) is sys_._last_T_kf


def test_motion_prior_option_is_checked():
    with pytest.raises(ConfigError, match="motion_prior"):
        config_from_dict(GCSlamConfig, {"motion_prior": "imu"})
    with pytest.raises(ConfigError, match="motion_prior_max_gap"):
        config_from_dict(GCSlamConfig, {"motion_prior_max_gap": 0})


def test_motion_prior_stays_a_rigid_motion_when_the_step_is_not_quite_one():
    sys_ = GCSlam(GCSlamConfig(threaded=False))
    sys_.start(generate_sequence(SyntheticConfig(frames=2, height=60, width=80)))
    step = se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.02, 0.0], dtype=torch.float64))
    step[:3, :3] *= 1.001  # a registered pose rounded off SO(3)
    sys_._last_T_kf, sys_._last_time = torch.eye(4, dtype=torch.float64), 0.0
    sys_._update_velocity(step, 1 / 30)
    sys_._last_T_kf = step
    R = (torch.linalg.inv(step) @ sys_._predicted_T_kf(2 / 30))[:3, :3]  # the increment the prior adds
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)


@pytest.mark.parametrize("frontend", ["sparse", "dense"])
def test_a_weak_frame_promotes_the_previous_one_to_keyframe(monkeypatch, frontend):
    # Frames 12-14 claim to keep few correspondences (as blurred frames do): with
    # keyframe_weak_ratio the frame before the first of them becomes a keyframe, linked by its own
    # registration, and the weak frame is registered to it; no frame is recorded twice.
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="translate", seed=1, **SMALL))
    weak = {12, 13, 14}
    seen: list[int] = []
    cls = fe.frontend_class(Frontend(frontend))
    real = cls.register

    def register(self, keyframe, frame, T_guess):
        reg = real(self, keyframe, frame, T_guess)
        if seen[-1] in weak and keyframe is not None and keyframe.frame_index < 11:
            return dataclasses.replace(reg, correspondences=reg.correspondences // 10)
        return reg

    real_track = gc.GCSlam.track

    def track(self, frame):
        seen.append(frame.index)
        return real_track(self, frame)

    monkeypatch.setattr(cls, "register", register)
    monkeypatch.setattr(gc.GCSlam, "track", track)
    # ORB-measured pairs (keyframe_pairs=sparse): the promoted keyframe's pose is then its own
    # tracked registration's, which the assertions below compare; and the frames each posed by
    # their own keyframe alone (spread_corrections off), so that the frames before stay; ORB
    # poses as registered (depth_refine_points 0), whose optimum is the ORB pairs' own.
    kw = dict(frontend=frontend, loops=False, keyframe_pairs="sparse", spread_corrections=False, depth_refine_points=0)
    off, a_off = _run(seq, keyframe_weak_ratio=0, **kw)
    seen.clear()
    on, a_on = _run(seq, keyframe_weak_ratio=0.5, **kw)
    assert off.output.metrics["tracking"]["promoted_keyframes"] == 0
    assert on.output.metrics["tracking"]["promoted_keyframes"] == 1
    kfs = on.output.keyframe_indices.tolist()
    assert 11 in kfs and 11 not in off.output.keyframe_indices.tolist(), kfs
    assert on.output.frame_indices.tolist() == list(range(30))  # each frame posed once, in order
    # The frames before are untouched; the promoted one moves from its registration's pose to
    # its pair's optimum (sub-millimetre); the rest stays as accurate.
    torch.testing.assert_close(on.output.T_wc[:11], off.output.T_wc[:11], atol=1e-9, rtol=0)
    torch.testing.assert_close(on.output.T_wc[11], off.output.T_wc[11], atol=1e-3, rtol=0)
    assert a_on.stats["rmse"] < 0.01, a_on.stats


def test_keyframe_weak_ratio_is_checked():
    for bad in (-0.1, 1.0):
        with pytest.raises(ConfigError, match="keyframe_weak_ratio"):
            config_from_dict(GCSlamConfig, {"keyframe_weak_ratio": bad})


def test_a_promoted_keyframe_joins_mild_but_proposes_no_loops():
    from torchslam.registration.sparse import frame_features

    seq = generate_sequence(SyntheticConfig(frames=1, trajectory="translate", seed=1, **SMALL))
    frame = seq[0]
    feats = frame_features(frame.rgb, frame.depth, seq.camera)
    assert len(feats) > 100
    opt = go.Optimizer(GCSlamConfig(threaded=False), Monitor())
    p = torch.rand(1, 40, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) + 1
    stats, eye = PairStats.from_padded(p, p), torch.eye(4, dtype=torch.float64)
    assert opt.begin(go.KeyframeEvent(0, None, None, None, feats)) == []
    assert opt.begin(go.KeyframeEvent(1, 0, eye, stats, feats, promoted=True)) == []
    assert len(opt.mild) == 2  # it is in the place database all the same
    # The same view again: keyframe 0 is proposed (1 is the reference, never a loop candidate).
    assert opt.begin(go.KeyframeEvent(2, 1, eye, stats, feats)) == [0]


# ------------------------------------------------------------------ keyframe pairs measured densely


def test_keyframe_pairs_option_resolves_per_frontend_and_is_checked():
    assert GCSlamConfig().dense_pairs  # auto: dense pairs with either front-end
    assert GCSlamConfig(frontend="dense").dense_pairs
    assert not GCSlamConfig(frontend="dense", keyframe_pairs="sparse").dense_pairs
    assert not GCSlamConfig(keyframe_pairs="sparse").dense_pairs
    assert GCSlamConfig(frontend="dense", keyframe_pairs="dense").dense_pairs
    with pytest.raises(ConfigError, match="keyframe_pairs"):
        config_from_dict(GCSlamConfig, {"keyframe_pairs": "photometric"})


def _keyframe_pair(offset_m=0.03, angle_rad=0.03):
    """Two noise-free keyframes' images, their true ``T_01`` and an ORB-like pose off by a few cm / degrees."""
    seq = generate_sequence(SyntheticConfig(frames=7, depth_noise=False, trajectory="handheld", seed=2, batch_size=7, **SMALL))
    rgb, depth = seq.render([0, 6])
    T_01 = se3_inverse(seq.groundtruth.T_wc[0]) @ seq.groundtruth.T_wc[6]
    T_orb = se3_exp(torch.tensor([offset_m, -offset_m, 0.0, 0.0, angle_rad, 0.0], dtype=torch.float64)) @ T_01
    images = [dense_images(rgb[k : k + 1], depth[k : k + 1], seq.camera) for k in range(2)]
    return images, T_01, T_orb


def _pair_events(images, T_orb, refine=True):
    feats = FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3, dtype=torch.float64),
                          torch.zeros(0, dtype=torch.bool))
    # The ORB pair's statistics: a few exact correspondences of the (wrong) ORB pose.
    p_j = torch.rand(1, 60, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.5])
    orb = PairStats.from_padded(p_j @ T_orb[:3, :3].T + T_orb[:3, 3], p_j)
    return (go.KeyframeEvent(0, None, None, None, feats, None, images=images[0]),
            go.KeyframeEvent(1, 0, T_orb, orb, feats, None, images=images[1], refine=refine)), orb


def test_an_orb_pair_is_measured_again_densely_from_its_pose():
    images, T_01, T_orb = _keyframe_pair()
    opt = go.Optimizer(GCSlamConfig(threaded=False), Monitor())
    events, orb = _pair_events(images, T_orb)
    for ev in events:
        gc.insert_keyframe(opt, ev)
    assert opt.refined == {"odometry": 1, "loops": 0, "failed": 0}
    assert int(opt.stats[0].count) > 10_000 > int(orb.count)  # the dense correspondences' statistics
    # FastGO's optimum of the one pair is the dense pose: the ORB pose's 4.2 cm / 1.7 degree error is gone.
    err = se3_log(se3_inverse(T_01) @ opt.T_wk[1])
    assert err[:3].norm() < 2e-3 and err[3:].norm() < 1e-3, err
    assert opt.stage_ms["pair_refinement"] > 0


def test_a_failed_dense_measurement_keeps_the_orb_pair(monkeypatch):
    images, _, T_orb = _keyframe_pair()
    real = go.register_dense_frames

    def failing(fi, fj, T_init, cfg):
        res = real(fi, fj, T_init, cfg)
        return dataclasses.replace(res, success=torch.zeros_like(res.success))

    monkeypatch.setattr(go, "register_dense_frames", failing)
    opt = go.Optimizer(GCSlamConfig(threaded=False), Monitor())
    events, orb = _pair_events(images, T_orb)
    for ev in events:
        gc.insert_keyframe(opt, ev)
    assert opt.refined == {"odometry": 0, "loops": 0, "failed": 1}
    torch.testing.assert_close(opt.stats[0].S_ij, orb.S_ij, rtol=0, atol=0)
    torch.testing.assert_close(opt.T_wk[1], T_orb, rtol=0, atol=1e-9)


@pytest.mark.parametrize("keyframe_pairs,refine", [("sparse", True), ("dense", False)])
def test_orb_pairs_stay_where_dense_pairs_are_off_or_not_asked_for(keyframe_pairs, refine):
    images, _, T_orb = _keyframe_pair()
    opt = go.Optimizer(GCSlamConfig(threaded=False, keyframe_pairs=keyframe_pairs), Monitor())
    events, orb = _pair_events(images, T_orb, refine=refine)
    for ev in events:
        gc.insert_keyframe(opt, ev)
    assert opt.refined == {"odometry": 0, "loops": 0, "failed": 0}
    torch.testing.assert_close(opt.stats[0].S_ij, orb.S_ij, rtol=0, atol=0)
    # Only the dense setting keeps the keyframes' images (the rest need none).
    assert [im is not None for im in opt.images] == [keyframe_pairs == "dense"] * 2


def test_loop_pair_weight_option_resolves_per_frontend_and_is_checked():
    assert GCSlamConfig(frontend="dense").loops_at_orb_weight  # auto with the dense front-end: the ORB weight
    assert not GCSlamConfig().loops_at_orb_weight  # auto with the sparse one: the correspondences' own
    assert GCSlamConfig(loop_pair_weight="orb").loops_at_orb_weight
    assert not GCSlamConfig(frontend="dense", loop_pair_weight="correspondences").loops_at_orb_weight
    with pytest.raises(ConfigError, match="loop_pair_weight"):
        config_from_dict(GCSlamConfig, {"loop_pair_weight": "count"})


def test_densely_measured_loops_enter_fastgo_at_their_orb_weight(monkeypatch):
    """``loop_pair_weight=orb``: each densely measured loop keeps the dense correspondences'
    statistics (their count, their pose) scaled to the total weight of its ORB registration;
    ``correspondences`` keeps the dense weight, tens of times larger."""
    seq = generate_sequence(SyntheticConfig(frames=40, fps=10.0, trajectory="loop", seed=0, **SMALL))
    orb_n: list[float] = []
    optimizers: list[go.Optimizer] = []
    real_register, real_init = go.register_sparse_batch, go.Optimizer.__init__

    def register(*args, **kwargs):
        res = real_register(*args, **kwargs)
        orb_n.extend(float(res.stats.n[b]) for b in range(len(res.success)) if bool(res.success[b]))
        return res

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        optimizers.append(self)

    monkeypatch.setattr(go, "register_sparse_batch", register)
    monkeypatch.setattr(go.Optimizer, "__init__", init)
    loops = {}
    for weight in ("orb", "correspondences"):
        orb_n.clear()
        _, a = _run(seq, frontend="dense", keyframe_pairs="dense", loop_pair_weight=weight, mild={"top_k": 2})
        opt = optimizers[-1]
        stats = PairStats.cat(opt.stats)
        loops[weight] = stats[torch.tensor([kind == "loop" for kind in opt.pair_kind])]
        assert len(loops[weight]) and opt.refined["loops"] >= len(loops[weight]) and a.stats["rmse"] < 0.01
        assert (loops[weight].count > 1000).all()  # dense correspondences either way
        if weight == "orb":
            for n in loops[weight].n.tolist():
                assert min(abs(n - m) for m in orb_n) <= 1e-9 * n
    ratio = [(s.n / s.count).tolist() for s in (loops["orb"], loops["correspondences"])]
    assert max(ratio[0]) < 0.1 * min(ratio[1]), ratio


@pytest.mark.parametrize("frontend", ["sparse", "dense"])
def test_dense_keyframe_pairs_in_a_run(frontend):
    seq = generate_sequence(SyntheticConfig(frames=40, fps=10.0, trajectory="loop", seed=0, **SMALL))
    few = {"mild": {"top_k": 1}}  # one loop candidate per keyframe: the suite's time
    dense, a_dense = _run(seq, frontend=frontend, keyframe_pairs="dense", **few)
    orb, a_orb = _run(seq, frontend=frontend, keyframe_pairs="sparse", **few)
    m = dense.output.metrics
    assert m["keyframe_pairs"] == "dense" and orb.output.metrics["dense_pairs"] == {"odometry": 0, "loops": 0, "failed": 0}
    assert m["loops"]["registered"] >= 1
    # Every verified loop is measured densely; so is every odometry pair of the sparse front-end
    # (the dense front-end's are dense already: none is measured again, none relocalised here).
    assert m["dense_pairs"]["loops"] + m["dense_pairs"]["failed"] >= m["loops"]["registered"]
    odometry = m["pairs"]["odometry"] if frontend == "sparse" else 0
    assert m["dense_pairs"]["odometry"] + (m["dense_pairs"]["failed"] if frontend == "sparse" else 0) >= odometry
    assert m["tracking"]["relocalized"] == 0
    assert a_dense.stats["rmse"] < 0.01, a_dense.stats
    # auto is dense pairs for either front-end: the same run as keyframe_pairs=dense.
    auto, _ = _run(seq, frontend=frontend, **few)
    torch.testing.assert_close(auto.output.T_wc, dense.output.T_wc, rtol=0, atol=0)


def _noisy_chain(opt, n=6, seed=0):
    """Insert n keyframes into ``opt`` along an arc whose odometry pairs carry correspondence noise."""
    k = torch.arange(n, dtype=torch.float64)
    T_gt = se3_exp(torch.stack([0.2 * k, 0.03 * k, 0 * k, 0 * k, 0.05 * k, 0 * k], -1))
    feats = FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3, dtype=torch.float64),
                          torch.zeros(0, dtype=torch.bool))
    pairs = torch.stack([torch.arange(n - 1), torch.arange(1, n)], -1)
    p_i, p_j = make_correspondences(T_gt, pairs, 40, 0.01, torch.Generator().manual_seed(seed))
    for j in range(n):
        if j == 0:
            gc.insert_keyframe(opt, go.KeyframeEvent(0, None, None, None, feats, None))
        else:
            stats = PairStats.from_padded(p_i[j - 1 : j], p_j[j - 1 : j])
            gc.insert_keyframe(opt, go.KeyframeEvent(j, j - 1, se3_inverse(T_gt[j - 1]) @ T_gt[j], stats, feats, None))
    return T_gt


@pytest.mark.parametrize("every", [True, False])
def test_fastgo_runs_per_keyframe_only_where_asked_or_before_a_loop_test(monkeypatch, every):
    opt = go.Optimizer(GCSlamConfig(threaded=False, fastgo_every_keyframe=every), Monitor())
    tested = []
    monkeypatch.setattr(go.Optimizer, "close_loops",
                        lambda self, kf, cands, frame_index=0: tested.append((kf, len(self.fastgo_ms))))
    T_gt = _noisy_chain(opt)
    # Without loop candidates every keyframe is a leaf placed by its odometry pair: FastGO runs
    # after each one only when asked, and the poses are then the chain of the pairs.
    assert len(opt.fastgo_ms) == (len(T_gt) - 1 if every else 0)
    if not every:
        chain = [T_gt[0]]
        for j in range(1, len(T_gt)):
            chain.append(chain[-1] @ se3_inverse(T_gt[j - 1]) @ T_gt[j])
        torch.testing.assert_close(torch.stack(opt.T_wk), torch.stack(chain), rtol=0, atol=1e-12)
    # A keyframe with candidates is optimised first (its loop test compares against the optimum).
    monkeypatch.setattr(opt.mild, "query", lambda d: (torch.tensor([0]), torch.tensor([1.0])))
    runs = len(opt.fastgo_ms)
    k = len(T_gt)
    feats = opt.features[-1]
    ev = go.KeyframeEvent(k, k - 1, torch.eye(4, dtype=torch.float64), opt.stats[-1], feats, None)
    gc.insert_keyframe(opt, ev)
    assert tested == [(k, runs + 1)]

