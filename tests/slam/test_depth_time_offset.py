"""The depth stream's latency: planted in synthetic sequences, read by TUMSequence, estimated from the images."""

import json
import math

import pytest
import torch

from torchslam.app.calibrate_time import estimate_depth_time_offset
from torchslam.app.run import DataConfig, load_sequence
from torchslam.cli import main
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
from torchslam.data.tum import TUMSequence
from torchslam.errors import ConfigError

# Hand-held motion (a pan with shake) at 320x240: rotation that changes within a few frames.
_SMALL = dict(width=320, height=240, trajectory="handheld", depth_noise=False, seed=3)


def test_planted_latency_renders_depth_at_the_later_instant_and_leaves_colour():
    fps = 30.0
    base = generate_sequence(SyntheticConfig(frames=6, fps=fps, **_SMALL))
    late = generate_sequence(SyntheticConfig(frames=6, fps=fps, depth_time_offset=1.0 / fps, **_SMALL))
    for k in range(5):
        a, b, b_next = late[k], base[k], base[k + 1]
        assert torch.equal(a.rgb, b.rgb)
        # One frame period late: frame k's depth is the next frame's, to the renderer's rounding.
        assert torch.allclose(a.depth, b_next.depth, atol=1e-5)
        assert not torch.allclose(a.depth, b.depth, atol=1e-3)
        assert a.depth_timestamp is None and a.geometry_time == a.timestamp  # stamped alike: no jitter


def test_jittered_depth_stamps_travel_through_a_tum_folder(tmp_path):
    seq = generate_sequence(SyntheticConfig(frames=8, depth_stamp_jitter=0.012, **_SMALL))
    gap = seq.depth_timestamps - seq.timestamps
    assert float(gap.abs().max()) <= 0.012 and float(gap.abs().min()) > 0
    assert seq[3].depth_timestamp == pytest.approx(float(seq.depth_timestamps[3]), abs=0)
    out = write_tum_folder(seq, tmp_path / "seq")
    tum = TUMSequence(out)
    assert torch.allclose(tum.depth_timestamps, seq.depth_timestamps, atol=1e-6)
    assert tum.depth_time_offset == 0.0
    shifted = TUMSequence(out, depth_time_offset=-0.01)
    # The same pairs, each depth instant 10 ms before its stamp; colour stamps as written.
    assert shifted.depth_paths == tum.depth_paths and torch.equal(shifted.timestamps, tum.timestamps)
    assert torch.allclose(shifted.depth_timestamps, tum.depth_timestamps - 0.01, atol=1e-12)
    assert shifted[2].geometry_time == pytest.approx(float(tum.depth_timestamps[2]) - 0.01, abs=1e-12)


@pytest.mark.parametrize("value", [0.6, -1.0, math.nan, "x", True])
def test_a_bad_latency_is_refused_by_name(tmp_path, value):
    out = write_tum_folder(generate_sequence(SyntheticConfig(frames=2, **_SMALL)), tmp_path / "seq")
    with pytest.raises(ConfigError, match="depth_time_offset"):
        TUMSequence(out, depth_time_offset=value)
    with pytest.raises(ConfigError, match=r"data\.depth_time_offset: .*'auto'"):
        DataConfig(depth_time_offset=value)


def test_data_config_takes_auto_and_keeps_synthetic_data_apart():
    assert DataConfig(depth_time_offset="auto").depth_time_offset == "auto"
    assert DataConfig(depth_time_offset="-0.01").depth_time_offset == -0.01
    with pytest.raises(ConfigError, match="synthetic"):
        load_sequence("synthetic", DataConfig(depth_time_offset=0.01))


@pytest.fixture(scope="module")
def planted_folder(tmp_path_factory):
    """60 frames whose depth is taken 20 ms after its stamp, stamps up to 15 ms apart (as TUM fr1)."""
    seq = generate_sequence(SyntheticConfig(frames=60, depth_time_offset=0.02, depth_stamp_jitter=0.015, **_SMALL))
    return write_tum_folder(seq, tmp_path_factory.mktemp("planted") / "seq")


@pytest.mark.parametrize("planted", [0.0, -0.02])
def test_estimate_recovers_a_planted_latency(planted):
    seq = generate_sequence(SyntheticConfig(frames=60, depth_time_offset=planted, depth_stamp_jitter=0.015, **_SMALL))
    est = estimate_depth_time_offset(seq, frames=60)
    assert est.pairs == 57 and not est.at_edge
    assert est.offset == pytest.approx(planted, abs=0.003)
    if planted != 0.0:
        assert est.cost_at_offset < 0.7 * est.cost_at_zero
    d = est.to_dict()
    assert d["offset_s"] == est.offset and len(d["cost_deg"]) == len(d["offsets_s"]) == est.offsets.numel()


def test_estimate_splits_a_long_sequence_into_runs_and_rejects_bad_arguments():
    seq = generate_sequence(SyntheticConfig(frames=40, depth_time_offset=-0.02, **_SMALL))
    # Two runs of 12 frames, 9 colour pairs each; the runs' chains never join.
    est = estimate_depth_time_offset(seq, frames=24, windows=2)
    assert est.pairs == 18 and est.offset == pytest.approx(-0.02, abs=0.005)
    with pytest.raises(ConfigError, match="max_offset"):
        estimate_depth_time_offset(seq, max_offset=0.0)
    with pytest.raises(ConfigError, match="frame_gap"):
        estimate_depth_time_offset(seq, frame_gap=0)
    with pytest.raises(ConfigError, match="need more than frame_gap"):
        estimate_depth_time_offset(seq, frames=6, windows=2, frame_gap=3)


def test_auto_estimates_unsynchronised_folders_only(planted_folder, tmp_path):
    seq = load_sequence(str(planted_folder), DataConfig(prefetch=0, depth_time_offset="auto"))
    assert seq.depth_time_offset == pytest.approx(0.02, abs=0.003)
    # Stamped alike: synchronised by declaration, nothing estimated.
    synced = write_tum_folder(generate_sequence(SyntheticConfig(frames=4, depth_time_offset=0.02, **_SMALL)), tmp_path / "synced")
    assert load_sequence(str(synced), DataConfig(prefetch=0, depth_time_offset="auto")).depth_time_offset == 0.0


def test_cli_calibrate_time_depth_stream(planted_folder, capsys):
    assert main(["calibrate-time", "--data", str(planted_folder), "--stream", "depth", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["stream"] == "depth" and res["pairs"] == 57
    assert res["offset_s"] == pytest.approx(0.02, abs=0.003)
    assert main(["calibrate-time", "--data", str(planted_folder), "--stream", "depth", "--pairs", "30"]) == 0
    text = capsys.readouterr().out
    assert "data.depth_time_offset=0.02" in text and "depth" in text
    assert main(["calibrate-time", "--data", str(planted_folder), "--stream", "depth", "--attitude", "groundtruth"]) == 2
    assert "--attitude" in capsys.readouterr().err


def test_a_run_records_the_latency_it_used(planted_folder, tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--system", "nislam", "--data", str(planted_folder), "--out", str(out), "--max-frames", "6",
                 "--no-tensorboard", "--no-progress", "--set", "data.depth_time_offset=0.02"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["depth_time_offset_s"] == 0.02


def test_synthetic_jitter_must_keep_the_depth_stamps_increasing():
    with pytest.raises(ConfigError, match="depth_stamp_jitter"):
        SyntheticConfig(fps=30.0, depth_stamp_jitter=0.017)
    with pytest.raises(ConfigError, match="depth_time_offset"):
        SyntheticConfig(depth_time_offset=2.0)


def test_auto_falls_back_to_the_stamps_where_it_cannot_estimate(tmp_path, caplog):
    # Three frames hold no pair 3 frames apart: nothing to estimate from, and the run goes on.
    short = write_tum_folder(generate_sequence(SyntheticConfig(frames=3, depth_stamp_jitter=0.01, **_SMALL)), tmp_path / "short")
    with caplog.at_level("WARNING", logger="torchslam.app.run"):
        seq = load_sequence(str(short), DataConfig(prefetch=0, depth_time_offset="auto"))
    assert seq.depth_time_offset == 0.0 and len(seq) == 3
    assert "not estimated" in caplog.text and "using 0" in caplog.text


def test_info_shows_how_the_depth_stream_is_stamped_against_the_colour_one(tmp_path):
    from torchslam.data.tum import sequence_info

    seq = generate_sequence(SyntheticConfig(frames=6, depth_stamp_jitter=0.012, **_SMALL))
    info = sequence_info(write_tum_folder(seq, tmp_path / "seq"))
    expected = float((seq.depth_timestamps - seq.timestamps).mean())
    assert info["association_mean_depth_minus_colour_s"] == pytest.approx(expected, abs=2e-6)
