"""Attitude/camera clock offset: the rotation-agreement curve, planted offsets, NI-SLAM's use of it, the CLI."""

import dataclasses
import json
import math

import pytest
import torch

from torchslam.allocator import resolve_allocator
from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.geometry import so3_exp
from torchslam.imu.attitude import AttitudeStream
from torchslam.systems import run_sequence
from torchslam.systems.nislam import NISlam, NISlamConfig
from torchslam.app.calibrate_time import estimate_attitude_time_offset, rotation_agreement

from tests._helpers import EditedSequence


def _spinning_stream(rate_hz: float = 200.0, seconds: float = 3.0) -> AttitudeStream:
    """Rotation about a slowly turning axis at a varying rate: relative rotations differ for every offset."""
    t = torch.arange(0, seconds, 1.0 / rate_hz, dtype=torch.float64)
    phi = torch.stack([0.4 * torch.sin(1.3 * t), 0.3 * torch.sin(2.1 * t + 0.5), 0.5 * torch.sin(0.9 * t)], dim=-1)
    return AttitudeStream(t, so3_exp(phi), "imu")


@pytest.fixture(scope="module")
def orbit():
    # 4 s per turn: about 90 deg/s, so a 20 ms offset is a 1.8 deg attitude error.
    return generate_sequence(SyntheticConfig(frames=40, width=320, height=240, trajectory="orbit", period=4.0, seed=2))


def test_rotation_agreement_is_zero_at_the_planted_offset_and_grows_away_from_it():
    stream = _spinning_stream()
    t_i = torch.linspace(0.3, 2.4, 25, dtype=torch.float64)
    t_j = t_i + 0.1
    planted = 0.0175
    R, ok = stream.at(torch.cat([t_i, t_j]) + planted)
    assert ok.all()
    R_ij = R[:25].transpose(-1, -2) @ R[25:]
    offsets = torch.arange(-16, 17, dtype=torch.float64) * 0.0025  # -40 ... 40 ms
    cost = rotation_agreement(stream, t_i, t_j, R_ij, offsets)
    k = int(torch.argmin(cost))
    assert offsets[k] == pytest.approx(planted, abs=0.0025)
    assert float(cost[k]) < 0.05  # degrees; linear interpolation of the 200 Hz stream only
    assert bool((cost[:k].diff() <= 1e-9).all()) and bool((cost[k:].diff() >= -1e-9).all())
    # Offsets that leave the stream make pairs invalid; with none left the cost is inf.
    far = rotation_agreement(stream, t_i, t_j, R_ij, torch.tensor([100.0], dtype=torch.float64))
    assert math.isinf(float(far[0]))


@pytest.mark.parametrize("planted", [0.0, 0.02, -0.035])
def test_estimate_recovers_a_planted_offset_from_synthetic_images(orbit, planted):
    s = orbit.attitude
    # The stream's clock runs ``planted`` ahead: the image stamped t is at t + planted there.
    shifted = AttitudeStream(s.timestamps + planted, s.R_wc, s.source)
    est = estimate_attitude_time_offset(orbit, shifted, max_pairs=16, frame_gap=2)
    assert est.pairs == 16
    assert est.offset == pytest.approx(planted, abs=0.004) and not est.at_edge
    if planted != 0.0:
        assert est.cost_at_offset < est.cost_at_zero
    d = est.to_dict()
    assert d["offset_s"] == est.offset and len(d["cost_deg"]) == len(d["offsets_s"]) == est.offsets.numel()


def test_estimate_reports_a_minimum_on_the_edge_of_a_too_narrow_range(orbit):
    s = orbit.attitude
    shifted = AttitudeStream(s.timestamps - 0.035, s.R_wc, s.source)
    # 0.011 s is not a whole number of 2.5 ms steps: the grid ends at -0.010.
    est = estimate_attitude_time_offset(orbit, shifted, max_offset=0.011, max_pairs=8, frame_gap=2)
    assert est.at_edge and est.offset == pytest.approx(-0.010, abs=1e-12)


def test_estimate_rejects_bad_arguments(orbit):
    with pytest.raises(ConfigError, match="max_offset"):
        estimate_attitude_time_offset(orbit, orbit.attitude, max_offset=0.0)
    with pytest.raises(ConfigError, match="frame_gap"):
        estimate_attitude_time_offset(orbit, orbit.attitude, frame_gap=0)


def test_nislam_attitude_time_offset_undoes_a_shifted_stream():
    seq = generate_sequence(SyntheticConfig(frames=20, width=320, height=240, trajectory="orbit", period=4.0, seed=2))
    s = seq.attitude

    def cfg(offset=0.0):
        return config_from_dict(NISlamConfig, {"attitude": "imu", "attitude_time_offset": offset, "loop": {"enabled": False}})

    base = run_sequence(NISlam(cfg()), seq).output
    # The whole stream moves, the filter's inputs too (the acceleration compensation reads them).
    shifted = EditedSequence(seq, attitude=dataclasses.replace(s, timestamps=s.timestamps + 0.02))
    fixed = run_sequence(NISlam(cfg(0.02)), shifted).output
    wrong = run_sequence(NISlam(cfg()), shifted).output
    assert torch.equal(fixed.timestamps, base.timestamps)  # trajectories keep the image stamps
    assert fixed.metrics["attitude_time_offset_s"] == 0.02 and base.metrics["attitude_time_offset_s"] == 0.0
    assert torch.allclose(fixed.T_wc, base.T_wc, atol=1e-6)
    # Without the offset the first frame lies before the shifted stream (untracked) and the rest
    # take rotations 20 ms stale.
    assert len(wrong.T_wc) == len(base.T_wc) - 1
    assert not torch.allclose(wrong.T_wc, base.T_wc[1:], atol=1e-3)


def test_cli_calibrate_time(tmp_path, capsys):
    out = tmp_path / "seq"
    args = ["--frames", "24", "--width", "320", "--height", "240", "--trajectory", "orbit"]
    assert main(["synth", "--out", str(out), *args]) == 0
    capsys.readouterr()
    assert main(["calibrate-time", "--data", str(out), "--attitude", "groundtruth", "--pairs", "8", "--frame-gap", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["attitude_source"] == "groundtruth" and res["pairs"] == 8
    assert (res["threads"], res["threads_source"]) == (1, "policy")
    assert res["malloc"] == resolve_allocator()[0] and isinstance(res["malloc_applied"], bool)
    assert abs(res["offset_s"]) < 0.005
    assert main(["calibrate-time", "--data", str(out), "--attitude", "groundtruth", "--pairs", "4"]) == 0
    text = capsys.readouterr().out
    assert "attitude_time_offset=" in text and "offset" in text
    assert main(["calibrate-time", "--data", str(out), "--max-offset", "0"]) == 2
    assert "--max-offset" in capsys.readouterr().err
    assert main(["calibrate-time", "--data", str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err
