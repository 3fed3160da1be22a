"""NI-SLAM in lockstep: batched runs equal per-sequence runs; failures and Ctrl-C stay per sequence."""

import dataclasses

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data import Frame
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError, ShapeError
from torchslam.systems import RunResult, run_sequence
from torchslam.systems.lockstep import default_max_batch, run_lockstep
from torchslam.systems.nislam import NISlam, NISlamConfig, track_frames

from tests._helpers import EditedSequence, interrupt_at

TINY = dict(width=160, height=120, fps=10.0)
CFG = config_from_dict(NISlamConfig, {"min_valid_points": 100, "kcc": {"ortho_height": 90, "ortho_width": 120}})


def _sequences():
    # Three lengths and three motions; 10 Hz makes the motion between frames large enough for
    # keyframe changes (and re-matching after a lost keyframe) within a few frames.
    specs = [(14, "orbit", 0), (9, "translate", 1), (18, "loop", 2)]
    return [generate_sequence(SyntheticConfig(frames=n, trajectory=t, seed=s, **TINY)) for n, t, s in specs]


def _assert_same_run(single: RunResult, batched: RunResult, atol: float) -> None:
    a, b = single.output, batched.output
    assert torch.equal(a.frame_indices, b.frame_indices)
    assert torch.equal(a.keyframe_indices, b.keyframe_indices)
    torch.testing.assert_close(b.T_wc, a.T_wc, atol=atol, rtol=0)
    torch.testing.assert_close(b.keyframe_T_wc, a.keyframe_T_wc, atol=atol, rtol=0)
    assert b.metrics["fused_frames"] == a.metrics["fused_frames"]
    assert batched.frames_processed == single.frames_processed


def test_lockstep_equals_per_sequence_runs_for_different_lengths():
    seqs = _sequences()
    singles = [run_sequence(NISlam(CFG), s) for s in seqs]
    # The planted motions exercise new keyframes while the group runs together.
    assert sum(len(r.output.keyframe_indices) for r in singles) >= 5
    for max_batch in (3, 2):  # one (3, ...) batch; a batch of two and one of one
        results = run_lockstep(CFG, seqs, max_batch=max_batch)
        assert len(results) == 3
        for seq, single, got in zip(seqs, singles, results):
            assert isinstance(got, RunResult), got
            assert got.frames_processed == got.frames_total == len(seq) and not got.interrupted
            _assert_same_run(single, got, atol=1e-5)
        # wall_s is the group's; compute_s is each sequence's attributed share of it.
        assert len({r.wall_s for r in results}) == 1
        assert all(r.compute_s > 0 for r in results)
        assert sum(r.compute_s for r in results) <= results[0].wall_s


def test_b1_lockstep_is_the_single_run():
    seq = _sequences()[1]
    single = run_sequence(NISlam(CFG), seq)
    (got,) = run_lockstep(CFG, [seq])
    _assert_same_run(single, got, atol=0.0)
    assert torch.equal(got.output.T_wc, single.output.T_wc)


def test_a_failing_sequence_does_not_stop_the_others(monkeypatch):
    good, short, longer = _sequences()

    def bad_frame(f: Frame) -> Frame:  # a colour image with 4 channels fails in back-projection
        return dataclasses.replace(f, rgb=torch.cat([f.rgb, f.rgb[:1]])) if f.index == 4 else f

    def unreadable(f: Frame) -> Frame:
        if f.index == 3:
            raise OSError("frame 3: truncated PNG")
        return f

    # A failure inside the batched tracking call: the call is repeated per sequence and only the
    # sequence that caused it is dropped.
    class _PlantedFilter:  # any use of this keyframe filter fails, inside the batched call
        def __getattr__(self, name):
            raise RuntimeError("planted failure while stacking the keyframe")

    original = NISlam.start_match

    def failing_request(self, input, cloud):
        request = original(self, input, cloud)
        if self.sequence_name == "fails-in-tracking" and input.frame.index == 5:
            return dataclasses.replace(request, kf_filter=_PlantedFilter())
        return request

    monkeypatch.setattr(NISlam, "start_match", failing_request)
    seqs = [
        good,
        EditedSequence(short, bad_frame),
        EditedSequence(longer, unreadable),
        EditedSequence(longer, name="fails-in-tracking"),
    ]
    results = run_lockstep(CFG, seqs, max_batch=4)
    assert isinstance(results[1], ShapeError) and "rgb" in str(results[1])
    assert isinstance(results[2], OSError) and "truncated" in str(results[2])
    assert isinstance(results[3], RuntimeError) and "planted" in str(results[3])
    assert isinstance(results[0], RunResult) and results[0].frames_processed == len(good)
    _assert_same_run(run_sequence(NISlam(CFG), good), results[0], atol=1e-5)


def test_ctrl_c_finishes_every_sequence_with_what_it_has():
    a, b, c = _sequences()

    results = run_lockstep(CFG, [a, EditedSequence(b, interrupt_at(5)), c], max_batch=3)
    for r in results:
        # Every sequence had tracked frames 0..4 when the second one's frame 5 was requested.
        assert isinstance(r, RunResult) and r.interrupted
        assert r.frames_processed == 5 and r.output.frame_indices.tolist() == [0, 1, 2, 3, 4]
        assert torch.isfinite(r.output.T_wc).all()


def test_bad_arguments_name_themselves():
    seqs = _sequences()[:1]
    with pytest.raises(ConfigError, match="sequences: expected a non-empty list"):
        run_lockstep(CFG, [])
    with pytest.raises(ConfigError, match="system_cfg: expected the config of an available system, got dict"):
        run_lockstep({"attitude": "imu"}, seqs)
    with pytest.raises(ConfigError, match=r"monitors: expected one monitor per sequence \(1\), got 2"):
        run_lockstep(CFG, seqs, monitors=[None, None])
    with pytest.raises(ConfigError, match="max_batch: expected a positive integer"):
        run_lockstep(CFG, seqs, max_batch=0)
    with pytest.raises(ConfigError, match="max_frames: expected a non-negative integer"):
        run_lockstep(CFG, seqs, max_frames=-1)
    with pytest.raises(ShapeError, match=r"frames: expected one frame per system \(1\), got 2"):
        track_frames([NISlam(CFG)], [seqs[0][0], seqs[0][1]])


def test_max_frames_and_default_batch():
    seqs = _sequences()
    results = run_lockstep(CFG, seqs, max_frames=4)
    assert [r.frames_processed for r in results] == [4, 4, 4]
    assert all(len(r.output.T_wc) == 4 for r in results)
    # On the CPU the default batch holds CPU_BATCH_PIXELS of orthographic images; elsewhere all.
    assert default_max_batch(CFG, "cpu", 64) == 2**18 // (90 * 120)
    assert default_max_batch(NISlamConfig(), "cpu", 64) == 1
    assert default_max_batch(CFG, "cuda", 64) == 64


def test_gcslam_lockstep_equals_per_sequence_runs_with_joint_fastgo(monkeypatch):
    """GC-SLAM in lockstep: one FastGO call for all sequences' new keyframes, same results."""
    import torchslam.systems.gcslam.system as gc
    from torchslam.systems.gcslam import GCSlam, GCSlamConfig

    seqs = [
        generate_sequence(SyntheticConfig(frames=n, width=320, height=240, trajectory=kind, seed=seed))
        for n, kind, seed in ((16, "orbit", 1), (10, "translate", 2), (22, "loop", 3))
    ]
    cfg = GCSlamConfig(threaded=False)
    alone = [run_sequence(GCSlam(cfg), s).output for s in seqs]
    batches = []
    real = gc.optimize_batch

    def spy(problems, config=None):
        batches.append(len(problems))
        return real(problems, config)

    monkeypatch.setattr(gc, "optimize_batch", spy)
    results = run_lockstep(cfg, seqs)
    assert max(batches) >= 2  # keyframes of several sequences were optimised in one call
    for res, ref in zip(results, alone):
        assert not isinstance(res, BaseException), res
        assert torch.equal(res.output.keyframe_indices, ref.keyframe_indices)
        torch.testing.assert_close(res.output.T_wc, ref.T_wc, rtol=0, atol=1e-5)
        assert res.frames_processed == len(ref.T_wc)
