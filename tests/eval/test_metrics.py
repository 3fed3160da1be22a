"""ATE/RPE: evo as the independent oracle on real ground truth, planted solutions, bad input."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch

from torchslam.data import Trajectory, read_tum_trajectory
from torchslam.errors import ConfigError, ShapeError
from torchslam.eval import (
    AlignMode,
    DeltaUnit,
    EvaluationError,
    associate_trajectories,
    ate,
    error_statistics,
    format_report,
    metrics_dict,
    rpe,
    rpe_pairs,
)
from torchslam.geometry import se3_exp, se3_from_Rt, so3_exp

evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo (dev dependency) is the oracle for ATE/RPE")
from evo.core import filters, sync  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402
from evo.tools import file_interface  # noqa: E402

F64 = torch.float64
TOL = 1e-6
SEQUENCES = ("tum_fr1_xyz", "7scenes_redkitchen", "hololens_dvmvs")
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")
KINDS = ("rigid", "sim3", "drift")


def _seed(name: str, kind: str, salt: int = 0) -> int:
    return 100 * salt + 10 * SEQUENCES.index(name) + KINDS.index(kind)


# ----------------------------------------------------------------------------- helpers


def _gt(shared_data, name: str) -> Trajectory:
    return read_tum_trajectory(shared_data / name / "groundtruth.txt")


def _perturb(gt: Trajectory, kind: str, seed: int) -> Trajectory:
    """A perturbed copy of ``gt`` as the estimator under test, rounded through a TUM array.

    * ``rigid``: random world transform, per-pose noise (1 cm, 0.5 deg), identical stamps.
    * ``sim3``: scaled by 0.6, random world transform, noise; every second pose, stamps jittered
      by up to +-2 ms (so association does real work).
    * ``drift``: left-multiplied by an accumulating random-walk twist with a bias; stamps
      shifted by +3 ms.
    """
    g = torch.Generator().manual_seed(seed)
    T, t = gt.T_wc, gt.timestamps
    n = len(gt)
    T_world = se3_exp(torch.randn(6, generator=g, dtype=F64) * torch.tensor([1.0, 1, 1, 0.8, 0.8, 0.8], dtype=F64))
    noise = se3_exp(torch.randn(n, 6, generator=g, dtype=F64) * torch.tensor([0.01] * 3 + [0.009] * 3, dtype=F64))
    if kind == "rigid":
        T_est, t_est = T_world @ T @ noise, t.clone()
    elif kind == "sim3":
        scaled = se3_from_Rt(T[:, :3, :3], 0.6 * T[:, :3, 3])
        T_est = (T_world @ scaled @ noise)[::2]
        t_est = t[::2] + (torch.rand(t[::2].shape, generator=g, dtype=F64) - 0.5) * 0.004
    elif kind == "drift":
        bias = torch.tensor([0.001, -0.0005, 0.0008, 0.0004, 0.0002, -0.0003], dtype=F64)
        steps = torch.randn(n, 6, generator=g, dtype=F64) * 0.002 + bias
        T_est, t_est = se3_exp(torch.cumsum(steps, 0)) @ T, t + 0.003
    else:
        raise AssertionError(kind)
    return Trajectory.from_tum_array(Trajectory(t_est, T_est).to_tum_array())


def _evo(traj: Trajectory) -> PoseTrajectory3D:
    """The same poses as an evo trajectory, built from the TUM array (evo wants wxyz)."""
    a = traj.to_tum_array().numpy()
    return PoseTrajectory3D(positions_xyz=a[:, 1:4], orientations_quat_wxyz=a[:, [7, 4, 5, 6]], timestamps=a[:, 0])


def _evo_synced(est: Trajectory, gt: Trajectory, max_dt: float = 0.02):
    return sync.associate_trajectories(_evo(gt), _evo(est), max_diff=max_dt)


def _evo_ape(est: Trajectory, gt: Trajectory, align: str) -> tuple[dict, float]:
    ref, est_e = _evo_synced(est, gt)
    scale = 1.0
    if align != "none":
        _, _, scale = est_e.align(ref, correct_scale=align == "sim3")
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_e))
    return ape.get_all_statistics(), float(scale)


def _evo_rpe(est: Trajectory, gt: Trajectory, delta: int, relation, align: str, all_pairs: bool) -> dict:
    ref, est_e = _evo_synced(est, gt)
    if align != "none":
        est_e.align(ref, correct_scale=align == "sim3")
    m = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=all_pairs)
    m.process_data((ref, est_e))
    return m.get_all_statistics()


def _assert_stats(ours: dict, theirs: dict, what: str) -> None:
    for k in STATS:
        assert abs(ours[k] - float(theirs[k])) <= TOL, f"{what} {k}: torchslam {ours[k]!r} vs evo {theirs[k]!r}"


def _uniform(n: int, dt: float = 1 / 30, t0: float = 1000.0) -> torch.Tensor:
    return t0 + dt * torch.arange(n, dtype=F64)


def _random_traj(n: int, seed: int, stamps: torch.Tensor | None = None) -> Trajectory:
    g = torch.Generator().manual_seed(seed)
    xi = torch.cumsum(torch.randn(n, 6, generator=g, dtype=F64) * 0.05, 0)
    return Trajectory(_uniform(n) if stamps is None else stamps, se3_exp(xi))


# ----------------------------------------------------------------------------- evo oracle


@pytest.mark.parametrize("name", SEQUENCES)
@pytest.mark.parametrize("kind", KINDS)
def test_ate_matches_evo(shared_data, name, kind):
    gt = _gt(shared_data, name)
    est = _perturb(gt, kind, seed=_seed(name, kind))
    for align in ("se3", "sim3", "none"):
        ours = ate(est, gt, align=align)
        theirs, scale = _evo_ape(est, gt, align)
        assert ours.align == align
        assert ours.matched == (len(est) if kind != "rigid" else len(gt))
        _assert_stats(ours.stats, theirs, f"{name}/{kind} ATE align={align}")
        assert abs(ours.scale - scale) <= TOL
    if kind == "sim3":
        # The fitted scale undoes the planted 0.6, up to the shrinkage 1 cm noise causes on
        # fr1/xyz's ~10 cm excursions.
        assert ate(est, gt, align="sim3").scale == pytest.approx(1 / 0.6, rel=0.05)


@pytest.mark.parametrize("name", SEQUENCES)
@pytest.mark.parametrize("kind", KINDS)
def test_rpe_matches_evo(shared_data, name, kind):
    gt = _gt(shared_data, name)
    est = _perturb(gt, kind, seed=_seed(name, kind, salt=1))
    aligns = ("none", "sim3") if kind == "sim3" else ("none", "se3")
    for delta in (1, 10):
        for all_pairs in (False, True):
            for align in aligns:
                ours = rpe(est, gt, delta=delta, unit="frames", align=align, all_pairs=all_pairs)
                what = f"{name}/{kind} RPE delta={delta} all_pairs={all_pairs} align={align}"
                trans = _evo_rpe(est, gt, delta, evo_metrics.PoseRelation.translation_part, align, all_pairs)
                rot = _evo_rpe(est, gt, delta, evo_metrics.PoseRelation.rotation_angle_deg, align, all_pairs)
                _assert_stats(ours.trans_stats, trans, what + " translation")
                _assert_stats(ours.rot_stats, rot, what + " rotation")
                assert ours.align == align and ours.unit == "frames" and ours.delta == delta


def test_alignment_matches_evo(shared_data):
    gt = _gt(shared_data, "tum_fr1_xyz")
    est = _perturb(gt, "sim3", seed=3)
    ours = ate(est, gt, align="sim3")
    ref, est_e = _evo_synced(est, gt)
    r, t, s = est_e.align(ref, correct_scale=True)
    np.testing.assert_allclose(ours.T_align[:3, :3].numpy(), r, atol=1e-9)
    np.testing.assert_allclose(ours.T_align[:3, 3].numpy(), t, atol=1e-9)
    assert ours.scale == pytest.approx(s, abs=1e-9)


def test_association_matches_evo(shared_data):
    gt = _gt(shared_data, "tum_fr1_xyz")
    est = _perturb(gt, "sim3", seed=4)  # every second pose, stamps jittered by up to 2 ms
    ie, ig = associate_trajectories(est, gt, max_dt=0.02)
    # evo matches each stamp of the first list to its nearest in the second; with 2 ms jitter
    # against ~10 ms spacing that is one-to-one, so both rules must pick the same pairs.
    e_idx, g_idx = sync.matching_time_indices(est.timestamps.numpy(), gt.timestamps.numpy(), max_diff=0.02)
    assert ie.tolist() == list(e_idx) and ig.tolist() == list(g_idx)
    assert ie.tolist() == list(range(len(est))) and ig.tolist() == list(range(0, len(gt), 2))


@pytest.mark.parametrize("name", SEQUENCES)
def test_groundtruth_reads_like_evo(shared_data, name):
    ours = _gt(shared_data, name)
    theirs = file_interface.read_tum_trajectory_file(str(shared_data / name / "groundtruth.txt"))
    np.testing.assert_array_equal(ours.timestamps.numpy(), theirs.timestamps)
    np.testing.assert_allclose(ours.T_wc.numpy(), np.stack(theirs.poses_se3), atol=1e-12)


def test_rpe_frame_pairs_match_evo():
    poses = [np.eye(4)] * 23
    stamps = _uniform(23)
    for delta in (1, 4, 22, 23):
        for all_pairs in (False, True):
            ours = rpe_pairs(stamps, delta, "frames", all_pairs).tolist()
            assert ours == [list(p) for p in filters.filter_pairs_by_index(poses, delta, all_pairs)]


# ----------------------------------------------------------------------------- planted solutions


@pytest.mark.parametrize("align", list(AlignMode))
def test_identical_trajectories_give_zero(shared_data, align):
    gt = _gt(shared_data, "7scenes_redkitchen")
    a = ate(gt, gt, align=align)
    assert a.matched == len(gt) and a.align == align.value
    assert max(abs(a.stats[k]) for k in STATS) < 1e-9
    for delta in (1, 10):
        r = rpe(gt, gt, delta=delta, align=align)
        assert max(abs(r.trans_stats[k]) for k in STATS) < 1e-9
        assert max(abs(r.rot_stats[k]) for k in STATS) < 1e-9


def test_rigid_offset():
    gt = _random_traj(60, seed=1)
    offset = torch.tensor([0.3, -0.4, 1.2], dtype=F64)
    shifted = Trajectory(gt.timestamps, se3_from_Rt(gt.T_wc[:, :3, :3], gt.T_wc[:, :3, 3] + offset))
    assert ate(shifted, gt, align="se3").stats["max"] < 1e-9
    plain = ate(shifted, gt, align="none")
    torch.testing.assert_close(plain.errors, offset.norm().expand(60), rtol=0, atol=1e-12)
    assert plain.stats["rmse"] == pytest.approx(offset.norm().item(), abs=1e-12)
    assert plain.stats["std"] < 1e-12
    # A full rigid motion of the world frame: aligned ATE and every RPE vanish.
    T_off = se3_exp(torch.tensor([0.5, 0.1, -0.2, 0.3, -1.0, 2.0], dtype=F64))
    moved = Trajectory(gt.timestamps, T_off @ gt.T_wc)
    fit = ate(moved, gt, align="se3")
    assert fit.stats["max"] < 1e-9
    torch.testing.assert_close(fit.T_align, torch.linalg.inv(T_off), rtol=0, atol=1e-9)
    for align in AlignMode:
        r = rpe(moved, gt, delta=3, align=align)
        assert r.trans_stats["max"] < 1e-9 and r.rot_stats["max"] < 1e-7


def test_sim3_planted_scale():
    gt = _random_traj(40, seed=2)
    T_off = se3_exp(torch.tensor([1.0, 2.0, -0.5, 0.2, 0.4, -0.1], dtype=F64))
    small = Trajectory(gt.timestamps, T_off @ se3_from_Rt(gt.T_wc[:, :3, :3], 0.25 * gt.T_wc[:, :3, 3]))
    fit = ate(small, gt, align="sim3")
    assert fit.stats["max"] < 1e-9 and fit.scale == pytest.approx(4.0, abs=1e-9)
    assert ate(small, gt, align="se3").stats["rmse"] > 0.01
    assert rpe(small, gt, delta=2, align="sim3").trans_stats["max"] < 1e-9
    # Without the scale the relative translations are 4x too short: error = 0.75 * |gt step|.
    r = rpe(small, gt, delta=2, align="none")
    steps = (gt.T_wc[2::2, :3, 3] - gt.T_wc[:-2:2, :3, 3]).norm(dim=-1)
    torch.testing.assert_close(r.trans_errors, 0.75 * steps, rtol=0, atol=1e-12)
    assert r.rot_stats["max"] < 1e-7


def test_rpe_planted_rotation_and_translation():
    # est = gt with one extra body-frame motion `kick` inside step 4 -> 5, so that
    # est_4^-1 est_5 = (gt_4^-1 gt_5) kick and every other step is unchanged: E_45 = kick.
    gt = _random_traj(10, seed=3)
    axis_angle = torch.tensor([0.0, 0.0, math.radians(7.0)], dtype=F64)
    kick = se3_from_Rt(so3_exp(axis_angle), torch.tensor([0.0, 0.02, 0.0], dtype=F64))
    T_est = gt.T_wc.clone()
    T_est[5:] = gt.T_wc[5] @ kick @ torch.linalg.inv(gt.T_wc[5]) @ gt.T_wc[5:]
    r = rpe(Trajectory(gt.timestamps, T_est), gt, delta=1)
    expected_rot = torch.zeros(9, dtype=F64)
    expected_rot[4] = 7.0
    expected_trans = torch.zeros(9, dtype=F64)
    expected_trans[4] = 0.02
    torch.testing.assert_close(r.rot_errors, expected_rot, rtol=0, atol=1e-9)
    torch.testing.assert_close(r.trans_errors, expected_trans, rtol=0, atol=1e-12)
    # Over two steps the kick is still the whole relative error (it sits inside each pair).
    r2 = rpe(Trajectory(gt.timestamps, T_est), gt, delta=2, all_pairs=True)
    torch.testing.assert_close(r2.rot_errors[[3, 4]], torch.full((2,), 7.0, dtype=F64), rtol=0, atol=1e-9)


def test_rotation_angle_near_pi():
    # A pure rotation of 179.9999 degrees between the two estimates of one pair.
    gt = Trajectory(_uniform(2), torch.eye(4, dtype=F64).expand(2, 4, 4).clone())
    R = so3_exp(torch.tensor([math.radians(179.9999), 0.0, 0.0], dtype=F64))
    est = Trajectory(gt.timestamps, torch.stack([torch.eye(4, dtype=F64), se3_from_Rt(R, torch.zeros(3, dtype=F64))]))
    assert rpe(est, gt).rot_stats["max"] == pytest.approx(179.9999, abs=1e-9)


def test_shifted_timestamps():
    gt = _random_traj(50, seed=4)
    late = Trajectory(gt.timestamps + 0.005, gt.T_wc.clone())
    ie, ig = associate_trajectories(late, gt)
    assert ie.tolist() == ig.tolist() == list(range(50))
    assert ate(late, gt, align="none").stats["max"] == 0.0
    # Correcting the clock with `offset` lets a much tighter gap work.
    ie, ig = associate_trajectories(late, gt, max_dt=0.001, offset=-0.005)
    assert ie.numel() == 50 and ate(late, gt, max_dt=0.001, offset=-0.005).matched == 50
    with pytest.raises(EvaluationError, match=r"closest gap is 0\.005000 s"):
        ate(late, gt, max_dt=0.004)


def test_unique_association_is_one_to_one():
    # Two estimated stamps 4 ms and 6 ms after each ground-truth stamp: only the nearer matches.
    gt = _random_traj(20, seed=5)
    stamps = torch.stack([gt.timestamps + 0.004, gt.timestamps + 0.006], 1).reshape(-1)
    est = Trajectory(stamps, gt.T_wc.repeat_interleave(2, 0))
    ie, ig = associate_trajectories(est, gt, max_dt=0.02, association="unique")
    assert ie.tolist() == list(range(0, 40, 2)) and ig.tolist() == list(range(20))


def test_seconds_pairs_brute_force():
    g = torch.Generator().manual_seed(6)
    stamps = 1.3e9 + torch.cumsum(torch.rand(200, generator=g, dtype=F64) * 0.05 + 0.001, 0)
    t = stamps.tolist()
    for delta in (0.01, 0.1, 0.77, 3.0):
        nxt = {}
        for i in range(len(t)):
            for j in range(i + 1, len(t)):
                if t[j] - t[i] >= delta:
                    nxt[i] = j
                    break
        assert rpe_pairs(stamps, delta, "seconds", all_pairs=True).tolist() == [[i, j] for i, j in nxt.items()]
        chain, i = [], 0
        while i in nxt:
            chain.append([i, nxt[i]])
            i = nxt[i]
        assert rpe_pairs(stamps, delta, DeltaUnit.SECONDS, all_pairs=False).tolist() == chain


def test_seconds_equal_frames_on_uniform_stamps(shared_data):
    # 7-Scenes stamps are frame_index / 30: 9.5/30 s always lands on the 10th next frame.
    gt = _gt(shared_data, "7scenes_redkitchen")
    est = _perturb(gt, "drift", seed=7)
    for all_pairs in (False, True):
        by_frames = rpe(est, gt, delta=10, unit="frames", all_pairs=all_pairs)
        by_seconds = rpe(est, gt, delta=9.5 / 30, unit="seconds", all_pairs=all_pairs)
        assert by_seconds.unit == "seconds"
        torch.testing.assert_close(by_seconds.pairs, by_frames.pairs, rtol=0, atol=0)
        torch.testing.assert_close(by_seconds.trans_errors, by_frames.trans_errors, rtol=0, atol=0)
        torch.testing.assert_close(by_seconds.rot_errors, by_frames.rot_errors, rtol=0, atol=0)


@pytest.mark.parametrize("k", [1, 2, 7, 8])
def test_error_statistics_vs_numpy(k):
    e = torch.rand(k, generator=torch.Generator().manual_seed(k), dtype=F64)
    s = error_statistics(e)
    x = e.numpy()
    ref = {
        "rmse": math.sqrt(np.mean(x**2)), "mean": np.mean(x), "median": np.median(x), "std": np.std(x),
        "min": np.min(x), "max": np.max(x), "sse": np.sum(x**2),
    }
    for key in STATS:
        assert s[key] == pytest.approx(ref[key], abs=1e-15)


def test_float32_input_is_evaluated_in_float64():
    gt = _random_traj(30, seed=8)
    est32 = Trajectory(gt.timestamps, (se3_exp(torch.tensor([0.1, 0, 0, 0, 0, 0.2], dtype=F64)) @ gt.T_wc).float())
    a = ate(est32, gt, align="none")
    assert a.errors.dtype == F64 and a.T_align.dtype == F64
    ref = ate(Trajectory(gt.timestamps, est32.T_wc.double()), gt, align="none")
    torch.testing.assert_close(a.errors, ref.errors, rtol=0, atol=0)


# ----------------------------------------------------------------------------- reports


def test_report_and_metrics_dict(shared_data):
    gt = _gt(shared_data, "hololens_dvmvs")
    est = _perturb(gt, "drift", seed=9)
    a = ate(est, gt, align="sim3")
    r = rpe(est, gt, delta=1, align="se3")
    text = format_report(a, r)
    assert "ATE alignment: sim3" in text and "RPE alignment: se3" in text
    assert f"| ATE | sim3 | {a.stats['rmse']:.6f} |" in text
    assert f"| RPE rotation | se3 | {r.rot_stats['rmse']:.6f} |" in text
    assert "RPE" not in format_report(a)
    d = json.loads(json.dumps(metrics_dict(a, r)))
    assert d["ate_rmse_m"] == a.stats["rmse"] and d["ate_median_m"] == a.stats["median"]
    assert d["ate_sse_m2"] == a.stats["sse"] and d["ate_scale"] == a.scale
    assert d["rpe_trans_rmse_m"] == r.trans_stats["rmse"] and d["rpe_rot_rmse_deg"] == r.rot_stats["rmse"]
    assert d["align"] == "sim3" and d["rpe_align"] == "se3" and d["matched"] == len(gt) == d["rpe_matched"]
    assert d["rpe_pairs"] == len(gt) - 1 and d["rpe_unit"] == "frames" and d["rpe_delta"] == 1
    assert set(metrics_dict(a)) == {k for k in d if not k.startswith("rpe_")}
    assert json.loads(json.dumps(a.to_dict(with_errors=True)))["errors"] == a.errors.tolist()
    assert r.to_dict()["rot_stats_deg"] == r.rot_stats


# ----------------------------------------------------------------------------- bad input


def test_no_overlap_raises_with_counts():
    gt = _random_traj(10, seed=10)
    est = Trajectory(gt.timestamps + 100.0, gt.T_wc)
    with pytest.raises(EvaluationError, match=r"est has 10 stamps .* gt has 10 stamps .* closest gap is 99\.7"):
        ate(est, gt)
    with pytest.raises(EvaluationError, match="no timestamps match"):
        rpe(est, gt)
    empty = Trajectory(torch.zeros(0, dtype=F64), torch.zeros(0, 4, 4, dtype=F64))
    with pytest.raises(EvaluationError, match="est has 0 stamps"):
        ate(empty, gt)


def test_wrong_types_and_shapes_raise():
    gt = _random_traj(10, seed=11)
    with pytest.raises(ShapeError, match="est: expected a Trajectory, got Tensor"):
        ate(gt.T_wc, gt)
    with pytest.raises(ShapeError, match="gt: expected a Trajectory"):
        rpe(gt, None)
    bad = copy.copy(gt)
    object.__setattr__(bad, "T_wc", gt.T_wc[:, :3, :])
    with pytest.raises(ShapeError, match=r"gt\.T_wc: expected \(N, 4, 4\)"):
        ate(gt, bad)
    with pytest.raises(ShapeError, match=r"T_wc: expected \(N, 4, 4\)"):
        Trajectory(gt.timestamps, gt.T_wc[:, :3, :])
    with pytest.raises(ShapeError, match="ate_result: expected an ATEResult"):
        format_report({"rmse": 1.0})


def test_bad_options_list_valid_ones():
    gt = _random_traj(10, seed=12)
    with pytest.raises(ConfigError, match=r"align: 'affine' is not one of \['se3', 'sim3', 'none'\]"):
        ate(gt, gt, align="affine")
    with pytest.raises(ConfigError, match=r"unit: 'metres' is not one of \['frames', 'seconds'\]"):
        rpe(gt, gt, unit="metres")
    with pytest.raises(ConfigError, match="delta: with unit='frames' expected a positive integer"):
        rpe(gt, gt, delta=1.5)
    with pytest.raises(ConfigError, match="delta: with unit='frames' expected a positive integer"):
        rpe(gt, gt, delta=0)
    with pytest.raises(ConfigError, match="delta: with unit='seconds' expected a positive duration"):
        rpe(gt, gt, delta=-0.1, unit="seconds")
    with pytest.raises(ConfigError, match="max_dt: must be >= 0"):
        ate(gt, gt, max_dt=-1)
    assert ate(gt, gt, align="SIM3").align == "sim3"


def test_degenerate_cases_raise():
    gt = _random_traj(10, seed=13)
    with pytest.raises(EvaluationError, match="no pose pair is 10 frames apart among the 10 matched poses"):
        rpe(gt, gt, delta=10)
    with pytest.raises(EvaluationError, match="no pose pair is 5.0 seconds apart"):
        rpe(gt, gt, delta=5.0, unit="seconds")
    two = gt.slice(slice(0, 2))
    with pytest.raises(EvaluationError, match="align='se3' needs at least 3 matched poses, got 2"):
        ate(two, gt)
    assert ate(two, gt, align="none").stats["max"] == 0.0
    still = Trajectory(gt.timestamps, gt.T_wc[:1].expand(10, 4, 4).clone())
    with pytest.raises(EvaluationError, match="sim3.*do not move"):
        ate(still, gt, align="sim3")


# ----------------------------------------------------------------------------- evo's association


def _evo_ape_files(gt_path, est_path, max_diff: float = 0.01, offset: float = 0.0) -> tuple[float, int]:
    """``evo_ape tum gt est -a --t_max_diff max_diff --t_offset offset``: (rmse, matched poses)."""
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff, offset_2=offset)
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(evo_metrics.StatisticsType.rmse)), est.num_poses


def _stamps_like_a_camera(gt: Trajectory, seed: int, step: int) -> torch.Tensor:
    """Every ``step``-th ground-truth stamp jittered by up to +-12 ms: some fall outside 10 ms."""
    g = torch.Generator().manual_seed(seed)
    t = gt.timestamps[::step]
    return t + (torch.rand(t.shape, generator=g, dtype=F64) - 0.5) * 0.024


@pytest.mark.parametrize("name", SEQUENCES)
def test_default_association_and_ate_are_evos_to_1e9(shared_data, tmp_path, name):
    gt_path = shared_data / name / "groundtruth.txt"
    gt = read_tum_trajectory(gt_path)
    base = _perturb(gt, "drift", seed=_seed(name, "drift", salt=7))
    cases = {
        "sparser": (_stamps_like_a_camera(gt, 1, 3), 0.0),
        # Denser than the ground truth: evo then starts from the ground truth's stamps.
        "denser": (torch.sort(torch.cat([gt.timestamps + 0.003, gt.timestamps[::2] - 0.004])).values, 0.0),
        "offset": (_stamps_like_a_camera(gt, 2, 2) + 0.05, -0.05),
    }
    for case, (stamps, offset) in cases.items():
        stamps = torch.unique(stamps)
        T, ok = base.interpolate(stamps)
        est = Trajectory.from_tum_array(Trajectory(stamps[ok], T[ok]).to_tum_array())
        path = tmp_path / f"{case}.txt"
        from torchslam.data import write_tum_trajectory

        write_tum_trajectory(path, est)
        est = read_tum_trajectory(path)
        ours = ate(est, gt, align="se3", offset=offset)
        rmse, matched = _evo_ape_files(gt_path, path, offset=offset)
        assert ours.matched == matched, case
        assert abs(ours.stats["rmse"] - rmse) <= 1e-9, f"{name}/{case}: {ours.stats['rmse']!r} vs evo {rmse!r}"
        assert ours.association == "nearest" and ours.max_dt == 0.01
        # The indices themselves are evo's.
        short_first = len(est) <= len(gt)
        if short_first:
            ie_evo, ig_evo = sync.matching_time_indices(est.timestamps.numpy(), gt.timestamps.numpy(), 0.01, -offset)
        else:
            ig_evo, ie_evo = sync.matching_time_indices(gt.timestamps.numpy(), est.timestamps.numpy(), 0.01, offset)
        ie, ig = associate_trajectories(est, gt, offset=offset)
        assert ie.tolist() == list(ie_evo) and ig.tolist() == list(ig_evo), case


def test_nearest_may_reuse_a_pose_where_unique_does_not():
    gt = _random_traj(20, seed=8)
    # Two estimated stamps 3 ms either side of each ground-truth stamp (the estimate is longer).
    stamps = torch.stack([gt.timestamps - 0.003, gt.timestamps + 0.003], 1).reshape(-1)
    est = Trajectory(stamps, gt.T_wc.repeat_interleave(2, 0))
    ie, ig = associate_trajectories(est, gt)  # evo: from the 20 ground-truth stamps, ties to the earlier
    e_idx, g_idx = sync.matching_time_indices(gt.timestamps.numpy(), est.timestamps.numpy(), 0.01)
    assert ig.tolist() == list(e_idx) == list(range(20)) and ie.tolist() == list(g_idx)
    # Fewer estimated poses than ground truth, two of them nearest to one ground-truth pose.
    short = Trajectory(gt.timestamps[[3, 3]] + torch.tensor([-0.004, 0.004], dtype=F64), gt.T_wc[[3, 3]])
    short = Trajectory(torch.cat([short.timestamps, gt.timestamps[10:12] + 0.001]), torch.cat([short.T_wc, gt.T_wc[10:12]]))
    ie, ig = associate_trajectories(short, gt)
    assert ig.tolist() == [3, 3, 10, 11]
    ie, ig = associate_trajectories(short, gt, association="unique")
    assert ig.tolist() == [3, 10, 11] and len(set(ig.tolist())) == len(ig)
    with pytest.raises(ConfigError, match=r"association: 'closest' is not one of \[.*'nearest', 'unique'"):
        ate(short, gt, association="closest")
