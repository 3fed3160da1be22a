"""Trajectory: TUM text round trip, SLERP interpolation against scipy, file:line errors."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from torchslam.data import Trajectory, read_tum_trajectory, write_tum_trajectory
from torchslam.errors import DataFormatError, ShapeError


def _random_trajectory(n: int, seed: int, t0: float = 1305031101.0, dt: float = 0.01) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.round(t0 + dt * np.arange(n) + rng.uniform(0, dt / 4, size=n), 6)
    R = Rotation.random(n, random_state=rng).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = rng.normal(scale=2.0, size=(n, 3))
    return Trajectory(torch.from_numpy(t), torch.from_numpy(T))


def test_write_read_round_trip(tmp_path):
    traj = _random_trajectory(50, seed=1)
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, traj, header="estimated by torchslam\nsecond line")
    text = path.read_text().splitlines()
    assert text[:2] == ["# estimated by torchslam", "# second line"]
    back = read_tum_trajectory(path)
    assert back.timestamps.dtype == torch.float64 and len(back) == 50
    # Timestamps are written with microseconds; epoch-scale values survive exactly at that resolution.
    np.testing.assert_allclose(back.timestamps.numpy(), traj.timestamps.numpy(), rtol=0, atol=5e-7)
    np.testing.assert_allclose(back.T_wc.numpy(), traj.T_wc.numpy(), rtol=0, atol=5e-9)
    # The file agrees with scipy's reading of the same numbers (quaternion xyzw, camera-to-world).
    rows = np.loadtxt(path, comments="#")
    np.testing.assert_allclose(Rotation.from_quat(rows[:, 4:8]).as_matrix(), traj.T_wc[:, :3, :3].numpy(), atol=5e-9)
    assert (rows[:, 7] >= 0).all()


def test_slerp_matches_scipy():
    traj = _random_trajectory(12, seed=2)
    t = traj.timestamps.numpy()
    rng = np.random.default_rng(3)
    alpha = np.concatenate([[0.5] * 11, rng.uniform(0, 1, size=11), [0.0, 1.0]])
    k = np.concatenate([np.arange(11), np.arange(11), [4, 4]])
    query = t[k] + alpha * (t[k + 1] - t[k])
    T, valid = traj.interpolate(torch.from_numpy(query))
    assert valid.all()
    slerp = Slerp(t, Rotation.from_matrix(traj.T_wc[:, :3, :3].numpy()))
    np.testing.assert_allclose(T[:, :3, :3].numpy(), slerp(query).as_matrix(), atol=1e-9)
    p = traj.positions.numpy()
    for d in range(3):
        np.testing.assert_allclose(T[:, d, 3].numpy(), np.interp(query, t, p[:, d]), atol=1e-9)
    np.testing.assert_allclose(T[:, 3].numpy(), np.tile([0, 0, 0, 1.0], (query.size, 1)), atol=0)


def test_interpolate_validity():
    t = torch.tensor([0.0, 0.01, 0.02, 0.2, 0.21], dtype=torch.float64)
    traj = Trajectory(t, torch.eye(4, dtype=torch.float64).expand(5, 4, 4).clone())
    q = torch.tensor([-0.001, 0.0, 0.015, 0.1, 0.205, 0.21, 0.3], dtype=torch.float64)
    _, valid = traj.interpolate(q, max_gap=0.05)
    assert valid.tolist() == [False, True, True, False, True, True, False]
    _, valid = traj.interpolate(q)
    assert valid.tolist() == [False, True, True, True, True, True, False]
    with pytest.raises(ShapeError, match="times: expected float64"):
        traj.interpolate(q.float())


def test_interpolate_at_a_gap_of_exactly_max_gap_on_epoch_stamps():
    # A 10 Hz stream at Unix-epoch stamps: the float64 gaps fall a few tenths of a microsecond
    # either side of 0.1 s (doubles near 1.3e9 are 2.4e-7 apart); every gap of such a stream is
    # max_gap = 0.1 and interpolated across; a gap 10 microseconds longer is not.
    t = 1305031102.175304 + torch.arange(40, dtype=torch.float64) * 0.1
    gaps = t.diff()
    assert bool((gaps > 0.1).any()) and bool((gaps < 0.1).any())  # the round-off the test is about
    traj = Trajectory(t, torch.eye(4, dtype=torch.float64).expand(40, 4, 4).clone())
    mid = (t[:-1] + t[1:]) / 2
    _, valid = traj.interpolate(mid, max_gap=0.1)
    assert bool(valid.all())
    _, valid = traj.interpolate(mid, max_gap=0.1 - 1e-5)
    assert not bool(valid.any())


@pytest.mark.parametrize(
    "row, match",
    [
        ("2.0 0 0 0 0 0 1", "expected 8 values"),
        ("2.0 0 0 0 0 0 0 1 5", "expected 8 values"),
        ("2.0 0 zero 0 0 0 0 1", "not a number"),
        ("2.0 nan 0 0 0 0 0 1", "NaN or infinite"),
        ("2.0 0 0 0 0 0 inf 1", "NaN or infinite"),
        ("2.0 0 0 0 0 0 0 0", "zero quaternion"),
        ("1.0 0 0 0 0 0 0 1", "duplicate timestamp"),
        ("0.5 0 0 0 0 0 0 1", "decreasing timestamp"),
    ],
)
def test_read_errors_name_file_and_line(tmp_path, row, match):
    path = tmp_path / "gt.txt"
    path.write_text("# header\n0.0 0 0 0 0 0 0 1\n\n1.0 0 0 0 0 0 0 1\n" + row + "\n")
    with pytest.raises(DataFormatError, match=re.escape(f"{path}:5: ") + match):
        read_tum_trajectory(path)


def test_read_missing_file(tmp_path):
    with pytest.raises(DataFormatError, match=re.escape(str(tmp_path / "absent.txt"))):
        read_tum_trajectory(tmp_path / "absent.txt")
