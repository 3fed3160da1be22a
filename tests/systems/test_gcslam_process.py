"""GC-SLAM's optimisation in a child process: the same results as the thread and inline, errors
raised in the tracker's place, progress and scalars carried back."""

from __future__ import annotations

import multiprocessing
import os

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError, TorchSlamError
from torchslam.features.matching import cpu_auto_backend
from torchslam.registration.sparse import FrameFeatures
from torchslam.systems import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.gcslam import optimizer as go
from torchslam.systems.gcslam import system as gc
from torchslam.systems.monitor import Monitor

pytestmark = pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="needs the fork start method")

SMALL = dict(width=320, height=240)


class _Recorder(Monitor):
    def __init__(self) -> None:
        self.tags: list[str] = []

    def scalar(self, tag, value, step) -> None:
        self.tags.append(tag)


def _run(seq, monitor=None, **cfg):
    system = GCSlam(config_from_dict(GCSlamConfig, cfg), monitor=monitor)
    return run_sequence(system, seq).output


def test_process_thread_and_inline_give_the_same_trajectory_and_loops():
    seq = generate_sequence(SyntheticConfig(frames=100, fps=10.0, trajectory="loop", seed=0, **SMALL))
    monitor = _Recorder()
    few = {"mild": {"top_k": 1}}  # one loop candidate per keyframe (about 50 loops here): the suite's time
    proc = _run(seq, monitor=monitor, threaded=True, background="process", **few)
    thread = _run(seq, threaded=True, background="thread", **few)
    inline = _run(seq, threaded=False, **few)
    assert (proc.metrics["background"], thread.metrics["background"], inline.metrics["background"]) == ("process", "thread", "inline")
    assert proc.metrics["loops"]["accepted"] >= 1
    for other in (thread, inline):
        assert torch.equal(proc.keyframe_indices, other.keyframe_indices)
        assert proc.metrics["loops"] == other.metrics["loops"]
        assert proc.metrics["pairs"] == other.metrics["pairs"]
        torch.testing.assert_close(proc.T_wc, other.T_wc, rtol=0, atol=1e-9)
    # The child's stage times and FastGO times come back; its scalars reach the parent's monitor.
    assert {"optimizer/fastgo", "optimizer/loop_registration"} <= set(proc.stage_ms)
    assert proc.metrics["fastgo_ms_last"] is not None
    assert "optimization/fastgo_ms" in monitor.tags and "progress/loops_accepted" in monitor.tags
    # Who matched: ``auto`` as resolved on this machine, the same in every run of the process.
    assert proc.metrics["match_backend"] == inline.metrics["match_backend"] == cpu_auto_backend().value


def test_metrics_name_a_forced_match_backend():
    seq = generate_sequence(SyntheticConfig(frames=12, fps=10.0, seed=1, **SMALL))
    out = _run(seq, threaded=False, sparse={"match_backend": "opencv"})
    assert out.metrics["match_backend"] == "opencv"


def _feats() -> FrameFeatures:
    return FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3, dtype=torch.float64),
                         torch.zeros(0, dtype=torch.bool))


def _event(k: int) -> go.KeyframeEvent:
    return go.KeyframeEvent(k, None, None, None, _feats(), None, frame_index=k)


def _optimizer() -> go.Optimizer:
    return go.Optimizer(GCSlamConfig(loops=False), Monitor())


def test_progress_reaches_the_parent_before_join():
    opt = _optimizer()
    worker = go.ProcessWorker(opt, gc.insert_keyframe)
    for k in range(3):
        worker.submit(_event(k))
    for _ in range(200):  # the child answers each keyframe; wait for all three
        worker.refresh()
        if len(opt.T_wk) == 3:
            break
        worker.process.join(timeout=0.02)
    assert len(opt.T_wk) == 3
    worker.join()
    assert not worker.process.is_alive() and worker.process.exitcode == 0
    assert len(opt.T_wk) == 3 and opt.pairs == []


def test_a_worker_dropped_without_join_lets_its_process_end():
    import gc as garbage

    worker = go.ProcessWorker(_optimizer(), gc.insert_keyframe)
    worker.submit(_event(0))
    process = worker.process
    del worker
    garbage.collect()
    process.join(timeout=30)
    assert process.exitcode == 0


def _fail_on_second(opt, ev):
    if ev.kf == 1:
        raise ValueError("planted failure in keyframe 1")
    gc.insert_keyframe(opt, ev)


def test_an_error_in_the_process_is_raised_in_the_trackers_place():
    worker = go.ProcessWorker(_optimizer(), _fail_on_second)
    worker.submit(_event(0))
    worker.submit(_event(1))
    with pytest.raises(TorchSlamError, match="planted failure in keyframe 1"):
        worker.join()


def _die(opt, ev):
    os._exit(3)


def test_a_process_that_dies_is_reported_with_its_exit_code():
    worker = go.ProcessWorker(_optimizer(), _die)
    worker.submit(_event(0))
    with pytest.raises(TorchSlamError, match="exit code 3"):
        worker.join()


def test_the_worker_follows_the_config_and_the_device():
    opt = _optimizer()
    cpu = torch.device("cpu")
    kinds = {
        "process": go.make_worker(opt, gc.insert_keyframe, GCSlamConfig(), cpu, deferred=False),
        "thread": go.make_worker(opt, gc.insert_keyframe, GCSlamConfig(background="thread"), cpu, deferred=False),
        "inline": go.make_worker(opt, gc.insert_keyframe, GCSlamConfig(threaded=False), cpu, deferred=False),
        "deferred": go.make_worker(opt, gc.insert_keyframe, GCSlamConfig(), cpu, deferred=True),
        "accelerator": go.make_worker(opt, gc.insert_keyframe, GCSlamConfig(), torch.device("meta"), deferred=False),
    }
    assert isinstance(kinds["process"], go.ProcessWorker)
    assert type(kinds["thread"]) is go.Worker and kinds["thread"].threaded
    assert type(kinds["inline"]) is go.Worker and not kinds["inline"].threaded
    assert kinds["deferred"].deferred and type(kinds["accelerator"]) is go.Worker
    for w in kinds.values():
        w.join()


def test_config_rejects_an_unknown_background():
    with pytest.raises(ConfigError, match="background"):
        GCSlamConfig(background="gpu")
