"""The frame log both systems keep: frames posed against keyframes, motion priors, re-sampling at frame times."""

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from tests._helpers import TOL, seeded
from torchslam.data.frame import Frame
from torchslam.geometry.lie import se3_exp, se3_inverse
from torchslam.systems.framelog import FrameLog

_DT = 1 / 30  # frame period, seconds
_JITTER = 0.012  # depth instants alternate this far before and after the colour stamps


def _frame(k: int, depth_offset: float | None = None) -> Frame:
    empty = torch.zeros(0)
    return Frame(index=k, timestamp=k * _DT, rgb=empty, depth=empty,
                 depth_timestamp=None if depth_offset is None else k * _DT + depth_offset)


def _planted(n: int = 12, every: int = 3, seed: int = 0):
    """n frames with random world poses, a keyframe every ``every`` frames; the log holds them relative to those."""
    g = seeded(seed)
    T_wc = se3_exp(0.5 * torch.randn(n, 6, generator=g, dtype=torch.float64))
    kf_frames = list(range(0, n, every))
    T_wk = T_wc[kf_frames]
    log = FrameLog()
    for k in range(n):
        kf = k // every
        log.record(_frame(k, _JITTER * (-1) ** k), kf, se3_inverse(T_wk[kf]) @ T_wc[k])
    return log, T_wc, T_wk


def test_poses_compose_the_keyframe_relative_poses():
    log, T_wc, T_wk = _planted()
    torch.testing.assert_close(log.poses(T_wk), T_wc, rtol=0, atol=TOL[torch.float64])
    # A keyframe correction moves every frame of that keyframe rigidly with it.
    g = seeded(1)
    C = se3_exp(0.1 * torch.randn(len(T_wk), 6, generator=g, dtype=torch.float64))
    moved = log.poses(C @ T_wk)
    for k in range(len(log)):
        kf = log.kf[k]
        torch.testing.assert_close(moved[k], C[kf] @ T_wc[k], rtol=0, atol=TOL[torch.float64])
    assert log.index == list(range(len(log)))
    assert log.geom_time == [k * _DT + _JITTER * (-1) ** k for k in range(len(log))]


def test_hold_repeats_the_last_pose_and_priors_are_counted_apart():
    log = FrameLog()
    assert not log.hold(_frame(0), "lost")  # no pose to hold yet
    assert len(log) == 0
    T = se3_exp(torch.tensor([0.1, 0.2, 0.3, 0.01, 0.02, 0.03], dtype=torch.float64))
    log.record(_frame(1), 0, torch.eye(4, dtype=torch.float64))
    log.record(_frame(2), 0, T)
    assert log.hold(_frame(3), "lost") and log.hold(_frame(4), "lost")
    log.record(_frame(5), 1, torch.eye(4, dtype=torch.float64), "unlinked")
    log.record(_frame(6), 1, T)
    assert log.kf == [0, 0, 0, 0, 1, 1]
    assert torch.equal(log.T_kf[2], T) and torch.equal(log.T_kf[3], T)
    assert log.n_prior() == 3
    assert log.prior_indices().tolist() == [3, 4, 5]
    assert log.prior_indices(lambda why, kf: why == "lost").tolist() == [3, 4]
    assert log.prior_indices(lambda why, kf: kf == 1).tolist() == [5]
    assert log.prior_indices().dtype == torch.int64
    assert FrameLog().prior_indices().shape == (0,)
    # The newest frame becoming keyframe 2: it is its own keyframe's origin.
    log.rebase_last(2)
    assert log.kf[-1] == 2 and torch.equal(log.T_kf[-1], torch.eye(4, dtype=torch.float64))


def test_so_far_is_the_prefix_of_frames_whose_keyframe_is_posed():
    log, T_wc, T_wk = _planted(n=10, every=4)  # keyframes 0, 1, 2 at frames 0, 4, 8
    assert log.so_far(T_wk[:0]) is None
    for K, n in ((1, 4), (2, 8), (3, 10)):
        traj = log.so_far(T_wk[:K])
        assert len(traj) == n
        torch.testing.assert_close(traj.T_wc, T_wc[:n], rtol=0, atol=TOL[torch.float64])
        assert traj.timestamps.dtype == torch.float64
        assert traj.timestamps.tolist() == log.geom_time[:n]


def _brute_force_resample(t_from: np.ndarray, T_from: np.ndarray, t_to: np.ndarray, max_gap: float) -> np.ndarray:
    """Per query: SLERP / linear between the bracketing instants (scipy), else the pose as it is."""
    out = T_from.copy()
    for m, t in enumerate(t_to):
        if t < t_from[0] or t > t_from[-1]:
            continue
        i = max(j for j in range(len(t_from) - 1) if t_from[j] < t or j == 0)
        if t_from[i + 1] - t_from[i] > max_gap:
            continue
        a = (t - t_from[i]) / (t_from[i + 1] - t_from[i])
        R = Slerp([0.0, 1.0], Rotation.from_matrix(T_from[[i, i + 1], :3, :3]))([a]).as_matrix()[0]
        out[m, :3, :3] = R
        out[m, :3, 3] = (1 - a) * T_from[i, :3, 3] + a * T_from[i + 1, :3, 3]
    return out


def test_at_frame_times_matches_a_float64_brute_force_reference():
    n = 14
    log, T_wc, T_wk = _planted(n=n, every=3, seed=2)
    # A gap in the depth instants longer than max_gap: the two frames around it stay as tracked.
    gap_log = FrameLog()
    for k in range(n):
        f = _frame(k, _JITTER * (-1) ** k)
        if k >= 8:
            f = Frame(index=k, timestamp=f.timestamp + 0.5, rgb=f.rgb, depth=f.depth, depth_timestamp=f.depth_timestamp + 0.5)
        gap_log.record(f, log.kf[k], log.T_kf[k])
    max_gap = 0.1
    for lg in (log, gap_log):
        T_geom = lg.poses(T_wk)
        got = lg.at_frame_times(T_geom, max_gap)
        ref = _brute_force_resample(np.array(lg.geom_time), T_geom.numpy(), np.array(lg.time), max_gap)
        torch.testing.assert_close(got, torch.from_numpy(ref), rtol=0, atol=1e-12)
        # The first colour stamp precedes the first depth instant: kept as tracked.
        torch.testing.assert_close(got[0], T_geom[0], rtol=0, atol=0)
        assert not torch.allclose(got[1:-1], T_geom[1:-1], atol=1e-6)
    got = gap_log.at_frame_times(gap_log.poses(T_wk), max_gap)
    torch.testing.assert_close(got[7], gap_log.poses(T_wk)[7], rtol=0, atol=0)  # its bracket spans the gap
    # Depth instants equal to the colour stamps: nothing to re-sample.
    same = FrameLog()
    for k in range(n):
        same.record(_frame(k), log.kf[k], log.T_kf[k])
    assert torch.equal(same.at_frame_times(same.poses(T_wk), max_gap), same.poses(T_wk))


def test_output_carries_the_log_and_empty_output_has_no_frames():
    log, T_wc, T_wk = _planted(n=6, every=3)
    out = log.output(T_wc, [0, 3], T_wk, None, None, {"track": 1.0}, {"m": 2}, log.prior_indices())
    assert out.frame_indices.tolist() == list(range(6)) and out.frame_indices.dtype == torch.int64
    assert out.timestamps.dtype == torch.float64 and out.timestamps.tolist() == log.time
    assert out.keyframe_indices.tolist() == [0, 3] and out.keyframe_T_wc is T_wk and out.T_wc is T_wc
    assert out.stage_ms == {"track": 1.0} and out.metrics == {"m": 2} and out.prior_indices.shape == (0,)
    empty = FrameLog.empty({"track": 0.5}, {"m": 1})
    assert empty.T_wc.shape == (0, 4, 4) and empty.frame_indices.shape == (0,)
    assert empty.stage_ms == {"track": 0.5} and empty.metrics == {"m": 1}


def _linked(n: int = 13, every: int = 4, seed: int = 3):
    """``_planted`` with every keyframe linked to the one before by the tracked pose between them."""
    log, T_wc, T_wk = _planted(n, every, seed)
    for k in range(1, len(T_wk)):
        log.link(k, k - 1, se3_inverse(T_wk[k - 1]) @ T_wk[k])
    return log, T_wc, T_wk


def _geodesic(T1: np.ndarray, T2: np.ndarray, frac: float) -> np.ndarray:
    """``T1 expm(frac logm(T1^-1 T2))`` by SciPy's matrix logarithm and exponential (float64)."""
    from scipy.linalg import expm, logm

    return T1 @ expm(frac * np.real(logm(np.linalg.solve(T1, T2))))


def test_spread_moves_each_frame_along_the_geodesic_to_its_pose_through_the_next_keyframe():
    every = 4
    log, T_wc, T_wk = _linked(every=every)  # keyframes 0..3 at frames 0, 4, 8, 12
    C = se3_exp(0.05 * torch.randn(len(T_wk), 6, generator=seeded(4), dtype=torch.float64))
    T_new = C @ T_wk  # each keyframe corrected differently: every link changed
    got = log.poses(T_new, spread=True).numpy()
    plain = log.poses(T_new).numpy()
    t = np.array(log.geom_time)
    for k in range(len(log)):
        a = log.kf[k]
        if a + 1 >= len(T_wk):  # the last keyframe's frames have nothing to follow
            np.testing.assert_allclose(got[k], plain[k], rtol=0, atol=1e-12)
            continue
        T_ref = (se3_inverse(T_wk[a]) @ T_wk[a + 1]).numpy()
        through_b = T_new[a + 1].numpy() @ np.linalg.solve(T_ref, log.T_kf[k].numpy())
        frac = (t[k] - t[a * every]) / (t[(a + 1) * every] - t[a * every])
        np.testing.assert_allclose(got[k], _geodesic(plain[k], through_b, frac), rtol=0, atol=1e-9)
    # Keyframes keep their poses exactly.
    for a in range(len(T_wk)):
        assert np.array_equal(got[a * every], plain[a * every])
    assert not np.allclose(got[1:every], plain[1:every], atol=1e-4)
    # The live estimate: the same over the keyframes posed so far; the last one's frames as they are.
    torch.testing.assert_close(log.so_far(T_new, spread=True).T_wc, torch.from_numpy(got), rtol=0, atol=0)
    part = log.so_far(T_new[:2], spread=True).T_wc  # keyframes 0 and 1: frames 0-7
    torch.testing.assert_close(part[:every], torch.from_numpy(got[:every]), rtol=0, atol=1e-12)
    torch.testing.assert_close(part[every:], torch.from_numpy(plain[every : 2 * every]), rtol=0, atol=1e-12)


def test_spread_of_a_translation_is_linear_in_time():
    log, T_wc, T_wk = _linked(n=9, every=4)
    shift = torch.tensor([0.03, -0.02, 0.01], dtype=torch.float64)
    T_new = T_wk.clone()
    T_new[1:, :3, 3] += shift  # keyframe 1 onwards moved: the link 0 -> 1 changed by a pure translation
    got = log.poses(T_new, spread=True)
    t = torch.tensor(log.geom_time)
    for k in range(1, 4):
        frac = (t[k] - t[0]) / (t[4] - t[0])
        torch.testing.assert_close(got[k, :3, 3], T_wc[k, :3, 3] + frac * shift, rtol=0, atol=1e-8)
        torch.testing.assert_close(got[k, :3, :3], T_wc[k, :3, :3], rtol=0, atol=1e-8)
    # Keyframe 1's frames: the link 1 -> 2 is kept, so they move rigidly with it.
    torch.testing.assert_close(got[4:8, :3, 3], T_wc[4:8, :3, 3] + shift, rtol=0, atol=1e-9)


def test_spread_changes_nothing_where_every_link_is_kept_or_missing():
    log, T_wc, T_wk = _linked()
    G = se3_exp(torch.tensor([0.3, -0.1, 0.2, 0.2, -0.4, 0.1], dtype=torch.float64))
    moved = G @ T_wk  # the whole graph moved rigidly: every link as tracked
    torch.testing.assert_close(log.poses(moved, spread=True), log.poses(moved), rtol=0, atol=1e-10)
    C = se3_exp(0.05 * torch.randn(len(T_wk), 6, generator=seeded(5), dtype=torch.float64))
    plain = FrameLog()  # no links: unlinked keyframes
    for k in range(len(log)):
        plain.record(_frame(k, _JITTER * (-1) ** k), log.kf[k], log.T_kf[k])
    assert torch.equal(plain.poses(C @ T_wk, spread=True), plain.poses(C @ T_wk))
    # A successor linked to another keyframe (a relocalisation) leaves its predecessor's frames be.
    reloc, _, _ = _planted(13, 4, 3)
    reloc.link(1, 0, se3_inverse(T_wk[0]) @ T_wk[1])
    reloc.link(2, 0, se3_inverse(T_wk[0]) @ T_wk[2])
    got, ref = reloc.poses(C @ T_wk, spread=True), reloc.poses(C @ T_wk)
    assert not torch.allclose(got[1:4], ref[1:4], atol=1e-4)  # keyframe 0 -> 1: spread
    torch.testing.assert_close(got[4:], ref[4:], rtol=0, atol=0)  # 1 -> 2 not linked to 1; 3 not linked
    assert log.poses(C @ T_wk, spread=False).equal(log.poses(C @ T_wk))
