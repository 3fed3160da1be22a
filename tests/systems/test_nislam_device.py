"""NI-SLAM on the simulated device (``diagnostics.device_audit``): what waits for the device, what stays there.

A tracking step of B sequences reads back from the device at most 3 times whatever B is (the
valid-point counts with the grey-warp flags, the match results, a retried match's results),
no device tensor meets a host tensor anywhere in a run (keyframes, loop closure and the final
map included), every stage's tensors live on the device, and the trajectory is the CPU's.
"""

from __future__ import annotations

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.diagnostics import DEVICE, device_audit, is_on_device
from torchslam.systems.nislam import NISlam, NISlamConfig
from torchslam.systems.nislam.step import backproject, match, track_frames

SMALL = {"kcc": {"ortho_height": 90, "ortho_width": 120}}


def _synthetic(seed: int, frames: int = 10):
    return generate_sequence(SyntheticConfig(frames=frames, trajectory="orbit", seed=seed, height=120, width=160))


def _run(sequences, cfg, device, audit=None):
    """Lockstep run; per step (syncs, mixes, whether a keyframe was made) when audited."""
    systems = [NISlam(cfg, device=device) for _ in sequences]
    for s, q in zip(systems, sequences):
        s.start(q)
    frames = [list(q) for q in sequences]
    steps = []
    for t in range(min(len(f) for f in frames)):
        before = [len(s.keyframes) for s in systems]
        if audit is not None:
            audit.clear()
        report = track_frames(systems, [f[t] for f in frames])
        assert report.errors == [None] * len(systems)
        if audit is not None:
            steps.append((len(audit.syncs), len(audit.mixed), before != [len(s.keyframes) for s in systems]))
    if audit is not None:
        audit.clear()
    outs = [s.finish() for s in systems]
    return outs, steps


@pytest.mark.parametrize("B", [1, 4])
def test_tracking_step_reads_back_at_most_three_times_whatever_the_batch(B):
    cfg = config_from_dict(NISlamConfig, {"attitude": "imu", "loop": {"enabled": True, "min_separation": 2}, **SMALL})
    seqs = [_synthetic(s) for s in range(B)]
    with device_audit() as audit:
        _, steps = _run(seqs, cfg, DEVICE, audit)
        finish_mixes = list(audit.mixed)
    tracking = [n for n, _, kf in steps[1:] if not kf]
    assert tracking, "no tracking step without a keyframe to measure"
    assert max(tracking) <= 3, (tracking, audit.summary())
    assert sum(m for _, m, _ in steps) == 0 and finish_mixes == []


def test_real_frames_with_lens_and_colour_instant(shared_data):
    """fr1/xyz: undistorted rays and grey sampled at the colour instant (the warp path), keyframes and loops."""
    from torchslam.data.tum import TUMSequence

    seq = TUMSequence(shared_data / "tum_fr1_xyz", end=16)
    cfg = config_from_dict(NISlamConfig, {
        "attitude": "groundtruth", "pixel_stride": 4, "kcc": {"ortho_height": 90, "ortho_width": 120, "T_K": 1.0e4, "T_M": 2.0e4},
        "loop": {"min_separation": 2},
    })
    with device_audit() as audit:
        (out,), steps = _run([seq], cfg, DEVICE, audit)
        finish_mixes = list(audit.mixed)
    assert any(kf for _, _, kf in steps[1:]), "the run made no keyframe after the first"
    # T_K above every PSR: each frame is lost, retried against a new keyframe and kept.
    assert sum(m for _, m, _ in steps) == 0 and finish_mixes == []
    (ref,), _ = _run([seq], cfg, "cpu")
    torch.testing.assert_close(out.T_wc.as_subclass(torch.Tensor), ref.T_wc, atol=1e-5, rtol=0)


def test_every_stage_returns_device_tensors():
    cfg = config_from_dict(NISlamConfig, {"attitude": "imu", "loop": {"enabled": False}, **SMALL})
    seqs = [_synthetic(s, frames=3) for s in range(2)]
    with device_audit():
        systems = [NISlam(cfg, device=DEVICE) for _ in seqs]
        for s, q in zip(systems, seqs):
            s.start(q)
        frames = [list(q) for q in seqs]
        track_frames(systems, [f[0] for f in frames])  # the first keyframes
        inputs = [s.prepare(f[1]) for s, f in zip(systems, frames)]
        assert all(is_on_device(w.rgb) and is_on_device(w.depth) for w in inputs)
        clouds = backproject(inputs)
        for c in clouds:
            assert is_on_device(c.points) and is_on_device(c.grey) and is_on_device(c.valid)
        requests = [s.start_match(w, c) for s, w, c in zip(systems, inputs, clouds)]
        results, filters, summaries = match(requests)
        for res, filt, summary in zip(results, filters, summaries):
            for name in ("t_content", "variance", "psr", "matched_fraction", "index", "depth_ok", "matched", "response"):
                assert is_on_device(getattr(res, name)), name
            assert is_on_device(res.frame.grey) and is_on_device(filt.h_hat) and is_on_device(filt.z_hat)
            assert not is_on_device(summary.t_content) and not is_on_device(summary.index)  # the host copy
        for s in systems:
            kf = s.keyframes[-1]
            assert is_on_device(kf.map.grey) and is_on_device(kf.resolution)
            assert not is_on_device(kf.T_wk)  # poses are host bookkeeping


def test_audited_run_equals_the_cpu_run():
    cfg = config_from_dict(NISlamConfig, {"attitude": "imu", **SMALL})
    seqs = [_synthetic(s, frames=8) for s in (0, 1)]
    with device_audit():
        outs, _ = _run(seqs, cfg, DEVICE)
    refs, _ = _run(seqs, cfg, "cpu")
    for out, ref in zip(outs, refs):
        torch.testing.assert_close(out.T_wc.as_subclass(torch.Tensor), ref.T_wc, atol=1e-5, rtol=0)


def test_learned_channels_stay_on_the_device_within_the_budget(tmp_path):
    """``kcc.features=learned``: the network moves with the correlator; no more read-backs, no mixes."""
    from torchslam.kcc import KCCFeatureNet
    from torchslam.learn import save_checkpoint

    torch.manual_seed(0)
    net = KCCFeatureNet(2, 4, initial_weight=0.5)
    ckpt = save_checkpoint(tmp_path / "features.pt", net, {"architecture": net.architecture()})
    cfg = config_from_dict(NISlamConfig, {"attitude": "imu", "kcc": {**SMALL["kcc"], "features": "learned",
                                                                     "features_weights": str(ckpt)}})
    seqs = [_synthetic(3, frames=8)]
    with device_audit() as audit:
        (out,), steps = _run(seqs, cfg, DEVICE, audit)
        finish_mixes = list(audit.mixed)
    tracking = [n for n, _, kf in steps[1:] if not kf]
    assert tracking and max(tracking) <= 3, (tracking, audit.summary())
    assert sum(m for _, m, _ in steps) == 0 and finish_mixes == []
    (ref,), _ = _run(seqs, cfg, "cpu")
    torch.testing.assert_close(out.T_wc.as_subclass(torch.Tensor), ref.T_wc, atol=1e-5, rtol=0)
