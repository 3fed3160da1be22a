"""Frames prepared ahead on another thread (``systems.base.AheadFrames``, ``prepare_ahead``).

The pipeline must hand out every frame in order, each prepared before it is handed out; pass
read errors on in the frame's place; leave a failed preparation to ``track``; stop its thread;
and leave the results of both systems exactly as without it.
"""

import threading

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.systems import run_sequence
from torchslam.systems.base import AheadFrames
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.nislam import NISlam, NISlamConfig

from tests._helpers import EditedSequence

SMALL = dict(width=320, height=240)


class _Recorder:
    """A system stand-in whose ``prepare_ahead`` records the frame and the thread it ran on."""

    prepares_ahead = True

    def __init__(self, fail_at: int | None = None):
        self.prepared: list[int] = []
        self.threads: set[str] = set()
        self.fail_at = fail_at

    def prepare_ahead(self, frame) -> None:
        self.threads.add(threading.current_thread().name)
        if frame.index == self.fail_at:
            raise RuntimeError("preparation failed")
        self.prepared.append(frame.index)


def _frames(n: int, fail_at: int | None = None):
    seq = generate_sequence(SyntheticConfig(frames=n, width=32, height=24, trajectory="translate"))
    for i in range(n):
        if i == fail_at:
            raise ValueError(f"frame {i}: unreadable")
        yield seq[i]


def test_every_frame_comes_out_in_order_prepared_on_another_thread():
    rec = _Recorder()
    ahead = AheadFrames(rec, _frames(7), depth=2)
    seen = []
    for frame in ahead:
        assert frame.index in rec.prepared, "a frame was handed out before its preparation finished"
        seen.append(frame.index)
    assert seen == list(range(7)) and rec.prepared == seen
    assert threading.current_thread().name not in rec.threads
    assert ahead.take_seconds() >= 0.0 and ahead.take_seconds() == 0.0


def test_a_read_error_is_raised_in_the_frames_place():
    ahead = AheadFrames(_Recorder(), _frames(6, fail_at=3))
    got = []
    with pytest.raises(ValueError, match="frame 3: unreadable"):
        for frame in ahead:
            got.append(frame.index)
    assert got == [0, 1, 2]


def test_a_failed_preparation_hands_the_frame_out_unprepared():
    rec = _Recorder(fail_at=2)
    assert [f.index for f in AheadFrames(rec, _frames(4))] == [0, 1, 2, 3]
    assert rec.prepared == [0, 1, 3]


def test_close_stops_the_thread_and_depth_is_checked():
    ahead = AheadFrames(_Recorder(), _frames(50), depth=1)
    next(ahead)
    thread = ahead._thread
    ahead.close()
    assert thread is not None and not thread.is_alive()
    with pytest.raises(StopIteration):
        next(ahead)
    with pytest.raises(ConfigError, match="depth"):
        AheadFrames(_Recorder(), _frames(1), depth=0)


def _count_ahead(system):
    calls = []
    original = system.prepare_ahead

    def spy(frame):
        calls.append(threading.current_thread().name)
        original(frame)

    system.prepare_ahead = spy
    return calls


def _run(make, seq, ahead: bool):
    system = make(ahead)
    calls = _count_ahead(system)
    result = run_sequence(system, seq)
    return result, calls


@pytest.mark.parametrize("frontend", ["sparse", "dense"])
def test_gcslam_gives_the_same_trajectory_with_frames_prepared_ahead(frontend):
    seq = generate_sequence(SyntheticConfig(frames=24, trajectory="orbit", seed=5, **SMALL))

    def make(ahead):
        return GCSlam(config_from_dict(GCSlamConfig, {"frontend": frontend, "threaded": False, "prepare_ahead": ahead, "prepare_ahead_in": "thread"}))

    off, calls_off = _run(make, seq, False)
    on, calls_on = _run(make, seq, True)
    assert calls_off == [] and len(calls_on) == len(seq)
    assert all(name == "torchslam-ahead" for name in calls_on)
    assert torch.equal(on.output.T_wc, off.output.T_wc)
    assert torch.equal(on.output.keyframe_indices, off.output.keyframe_indices)
    stage = "orb_extraction" if frontend == "sparse" else "dense_preparation"
    assert on.output.stage_ms[stage] > 0
    # The preparation's time is the sequence's compute too.
    assert on.compute_s >= on.output.stage_ms[stage] / 1000.0 * 0.99


def test_nislam_gives_the_same_trajectory_with_frames_prepared_ahead():
    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="orbit", seed=6, **SMALL))

    def make(ahead):
        return NISlam(config_from_dict(NISlamConfig, {"prepare_ahead": ahead}))

    off, calls_off = _run(make, seq, False)
    on, calls_on = _run(make, seq, True)
    assert calls_off == [] and len(calls_on) == len(seq)
    assert torch.equal(on.output.T_wc, off.output.T_wc)
    assert torch.equal(on.output.keyframe_indices, off.output.keyframe_indices)
    assert on.output.stage_ms["backproject"] > 0


def test_a_frame_whose_preparation_failed_is_tracked_inline_and_its_error_named():
    seq = generate_sequence(SyntheticConfig(frames=8, trajectory="translate", seed=2, **SMALL))

    def corrupt(frame):
        if frame.index == 5:
            frame = type(frame)(frame.index, frame.timestamp, frame.rgb, frame.depth[:, :10], frame.T_wc)
        return frame

    system = GCSlam(config_from_dict(GCSlamConfig, {"threaded": False}))
    with pytest.raises(Exception) as err:
        run_sequence(system, EditedSequence(seq, corrupt))
    # The same error as without the pipeline, raised by track in the frame's place.
    plain = GCSlam(config_from_dict(GCSlamConfig, {"threaded": False, "prepare_ahead": False}))
    with pytest.raises(type(err.value)) as err_plain:
        run_sequence(plain, EditedSequence(seq, corrupt))
    assert str(err.value) == str(err_plain.value)


def test_ahead_results_hand_a_frame_its_own_result_once():
    from torchslam.systems.base import AheadResults

    seq = generate_sequence(SyntheticConfig(frames=2, width=32, height=24, trajectory="translate"))
    first, again = seq[0], seq[0]  # equal index, other frame objects
    store, stage_ms = AheadResults(), {"backproject": 1.0}
    store.put(first, "cloud", {"backproject": 2.0})
    assert store.take(again, stage_ms) == (False, None) and stage_ms == {"backproject": 1.0}
    store.put(first, None, {"backproject": 2.0})  # None is a result too (an attitude gap)
    assert store.take(first, stage_ms) == (True, None) and stage_ms == {"backproject": 3.0}
    assert store.take(first, stage_ms) == (False, None)
