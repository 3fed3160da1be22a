"""Run-folder outputs: the voxel grid of map.ply, the headline ATE, strict JSON."""

import json

import pytest
import torch

from torchslam.systems.framelog import voxel_downsample


def _reference(points, colors, voxel):
    """Row-wise unique over integer voxel coordinates, then per-voxel means (float64)."""
    key = torch.floor(points.double() / voxel).to(torch.int64)
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    n = int(inv.max()) + 1
    cnt = torch.zeros(n, dtype=torch.float64).index_add_(0, inv, torch.ones(len(points), dtype=torch.float64))
    P = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, points.double()) / cnt[:, None]
    C = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, colors.double()) / cnt[:, None]
    return P.float(), C.float()


def test_voxel_downsample_equals_rowwise_unique_reference():
    g = torch.Generator().manual_seed(0)
    # Negative and positive coordinates, many points per voxel, and a far outlier.
    pts = torch.cat([torch.randn(20000, 3, generator=g, dtype=torch.float64) * 0.3 - 0.1,
                     torch.tensor([[250.0, -300.0, 7.0]], dtype=torch.float64)])
    cols = torch.rand(len(pts), 3, generator=g)
    for voxel in (0.01, 0.05):
        P, C = voxel_downsample(pts, cols, voxel)
        Pr, Cr = _reference(pts, cols, voxel)
        assert torch.equal(P, Pr) and torch.equal(C, Cr)
    P, C = voxel_downsample(pts, cols, 0.0)  # no downsampling
    assert torch.equal(P, pts.float()) and torch.equal(C, cols)
    # Spans too wide for one int64 key fall back to the row-wise unique.
    wide = torch.tensor([[0.0, 0.0, 0.0], [1e7, 1e7, 1e7], [1e7, 1e7, 1e7]], dtype=torch.float64)
    P, _ = voxel_downsample(wide, torch.zeros(3, 3), 1e-4)
    assert P.shape == (2, 3)


# ----------------------------------------------------------------------------- headline ATE


def _written_run(out, seq, T_wc, frames, system="nislam"):
    """Write a run folder for the poses ``T_wc`` of sequence frames ``frames`` (no SLAM involved)."""
    from torchslam.systems.base import RunResult, SystemOutput
    from torchslam.app.outputs import write_run

    idx = torch.as_tensor(frames, dtype=torch.int64)
    o = SystemOutput(
        frame_indices=idx, timestamps=seq.timestamps[idx].to(torch.float64), T_wc=T_wc,
        keyframe_indices=idx[:1], keyframe_T_wc=T_wc[:1],
    )
    result = RunResult(o, len(seq), len(idx), 0, [], 1.0, 1.0, False)
    return write_run(out, system, result, seq)


@pytest.mark.parametrize("name", ["tum_fr1_xyz", "7scenes_redkitchen", "hololens_dvmvs"])
def test_headline_ate_is_evo_ape_on_the_files(shared_data, tmp_path, name):
    """``ate_rmse_m`` equals ``evo_ape tum groundtruth.txt trajectory.txt -a`` to 1e-9 m."""
    sync = pytest.importorskip("evo.core.sync")
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    from torchslam.data.tum import TUMSequence
    from torchslam.geometry import se3_exp

    seq = TUMSequence(shared_data / name, prefetch=0)
    g = torch.Generator().manual_seed(3)
    frames = torch.nonzero(torch.isin(seq.timestamps, seq.groundtruth.timestamps)).flatten()[::3]
    T_gt = seq.groundtruth.T_wc[torch.searchsorted(seq.groundtruth.timestamps, seq.timestamps[frames])]
    drift = se3_exp(torch.cumsum(torch.randn(len(frames), 6, generator=g, dtype=torch.float64) * 0.003, 0))
    T_est = se3_exp(torch.tensor([0.3, -0.2, 0.1, 0.2, 0.1, -0.3], dtype=torch.float64)) @ drift @ T_gt
    m = _written_run(tmp_path, seq, T_est, frames)
    assert json.loads((tmp_path / "metrics.json").read_text())["ate_rmse_m"] == m["ate_rmse_m"]
    ref = file_interface.read_tum_trajectory_file(str(shared_data / name / "groundtruth.txt"))
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "trajectory.txt"))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    evo_rmse = float(ape.get_statistic(evo_metrics.StatisticsType.rmse))
    assert abs(m["ate_rmse_m"] - evo_rmse) <= 1e-9, (m["ate_rmse_m"], evo_rmse)
    assert m["matched"] == est.num_poses
    assert m["ate_association"] == "nearest" and m["ate_association_max_dt_s"] == 0.01
    assert m["ate_groundtruth"] == "groundtruth.txt"
    # The ATE against the ground truth interpolated at the frame stamps is kept apart.
    assert m["ate_rmse_interpolated_m"] is not None and m["ate_rmse_interpolated_m"] > 0


def test_synthetic_headline_uses_the_exact_ground_truth(tmp_path):
    from torchslam.data.synthetic import SyntheticConfig, generate_sequence

    seq = generate_sequence(SyntheticConfig(frames=8, width=64, height=48, trajectory="translate"))
    T = seq.groundtruth.T_wc.clone()
    T[:, 0, 3] += 0.01 * torch.arange(8, dtype=torch.float64)  # planted error, known ATE
    m = _written_run(tmp_path, seq, T, range(8))
    assert m["ate_association"] == "exact" and m["ate_association_max_dt_s"] == 0.0
    assert m["ate_groundtruth"] == "sequence" and m["matched"] == 8
    assert "ate_rmse_interpolated_m" not in m
    from torchslam.data import Trajectory
    from torchslam.eval import ate

    expect = ate(Trajectory(seq.timestamps, T), seq.groundtruth).stats["rmse"]
    assert m["ate_rmse_m"] == pytest.approx(expect, abs=1e-15) and m["ate_rmse_m"] > 1e-3


# ----------------------------------------------------------------------------- map.ply


def _read_ply(path):
    import numpy as np

    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    rec = np.frombuffer(data[end:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    xyz = torch.from_numpy(np.stack([rec["x"], rec["y"], rec["z"]], 1).astype("float64"))
    rgb = torch.from_numpy(np.stack([rec["r"], rec["g"], rec["b"]], 1).astype("int64"))
    return xyz, rgb


@pytest.mark.parametrize("system", ["nislam", "gcslam"])
def test_map_is_in_colour_and_in_the_trajectory_world_frame(tmp_path, system):
    """The first frame's depth points, posed by trajectory.txt's first pose, lie on map.ply."""
    from torchslam.data import read_tum_trajectory
    from torchslam.data.synthetic import SyntheticConfig, generate_sequence
    from torchslam.geometry import backproject_depth
    from torchslam.systems import run_sequence
    from torchslam.systems.gcslam import GCSlam, GCSlamConfig
    from torchslam.systems.nislam import NISlam, NISlamConfig
    from torchslam.app.outputs import write_run

    seq = generate_sequence(SyntheticConfig(frames=12, width=160, height=120, trajectory="translate", depth_noise=False))
    build = NISlam(NISlamConfig(attitude="groundtruth")) if system == "nislam" else GCSlam(GCSlamConfig(threaded=False, map_stride=1))
    write_run(tmp_path, system, run_sequence(build, seq), seq)
    traj = read_tum_trajectory(tmp_path / "trajectory.txt")
    kfs = read_tum_trajectory(tmp_path / "keyframes.txt")
    # One stated world for both systems: the first keyframe's camera frame.
    torch.testing.assert_close(kfs.T_wc[0], torch.eye(4, dtype=torch.float64), atol=1e-8, rtol=0)
    map_xyz, map_rgb = _read_ply(tmp_path / "map.ply")
    f0 = seq[0]
    pts, valid = backproject_depth(f0.depth[None].double(), seq.camera.as_tensor(torch.float64)[None])
    pts = pts[0][valid[0]][::7]
    T0 = traj.T_wc[0]
    world = pts @ T0[:3, :3].T + T0[:3, 3]
    near = torch.cdist(world, map_xyz).min(dim=1).values
    assert float(near.median()) < 0.01, float(near.median())
    # The gravity-aligned frame NI-SLAM tracks in is not the output frame: there they miss.
    R_wc0 = seq.groundtruth.T_wc[0, :3, :3]
    off = torch.cdist(pts @ R_wc0.T, map_xyz).min(dim=1).values
    assert float(off.median()) > 0.05
    # Colour, not grey: the synthetic scene's texture is coloured.
    chroma = (map_rgb.max(dim=1).values - map_rgb.min(dim=1).values).float()
    assert float((chroma > 10).float().mean()) > 0.5


def _fill_colour_reference(colour, has, want, rounds=16):
    """The map's colour filling as plain float64 torch rounds of padded 3x3 sums."""
    import torch.nn.functional as F

    colour, has = colour.clone(), has.clone()
    for _ in range(rounds):
        todo = want & ~has
        if not bool(todo.any()):
            break
        w = has.double()[None]
        sums = F.conv2d(F.pad(torch.cat([colour * w, w])[:, None], (1, 1, 1, 1)), torch.ones(1, 1, 3, 3, dtype=torch.float64))[:, 0]
        total, count = sums[:3], sums[3]
        new = todo & (count > 0)
        if not bool(new.any()):
            break
        colour = torch.where(new[None], total / count.clamp_min(1e-12), colour)
        has = has | new
    return colour, has


@pytest.mark.parametrize("rounds", [1, 3, 16])
def test_map_colour_filling_equals_the_round_by_round_reference(rounds):
    from torchslam.systems.nislam.system import _fill_colour

    g = torch.Generator().manual_seed(3)
    H, W = 37, 53
    colour = torch.rand(3, H, W, generator=g, dtype=torch.float64)
    has = torch.rand(H, W, generator=g) < 0.15
    has[:, :10] = False  # a band far from any colour: filled only over several rounds
    want = torch.rand(H, W, generator=g) < 0.8
    got_c, got_h = _fill_colour(colour, has, want, rounds)
    ref_c, ref_h = _fill_colour_reference(colour, has, want, rounds)
    assert torch.equal(got_h, ref_h) and bool((got_h & ~has).any())
    torch.testing.assert_close(got_c[:, got_h], ref_c[:, ref_h], rtol=1e-12, atol=1e-12)
    # Pixels that had a colour keep it exactly; the input is not modified.
    assert torch.equal(got_c[:, has], colour[:, has])
