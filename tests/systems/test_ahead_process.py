"""Frames read and prepared ahead in a child process (``systems.ahead_process``).

The tensors must come back with their values, dtypes and shapes, in memory of their own, the
same tensor object once; frames must come out in order with their payloads; a read error must
be raised in the frame's place, a failed preparation left to ``track``; frames the child's
reading skipped must reach the parent's sequence; ``close`` must stop the child; and GC-SLAM's
results must be exactly those of the thread and of no preparation ahead.
"""

import io
import json
import os

import numpy as np
import pytest
import torch

from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.systems import ahead_process, run_sequence
from torchslam.systems.ahead_process import _SlotPickler, dumps, loads
from torchslam.systems.base import AheadFrames
from torchslam.systems.gcslam import GCSlam, GCSlamConfig

from tests._helpers import copy_tum_frames
from tests.systems.test_ahead import _frames

pytestmark = pytest.mark.skipif(not ahead_process.available(), reason="needs the fork start method (Linux)")

SMALL = dict(width=320, height=240)


def test_tensors_travel_with_their_values_in_memory_of_their_own():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 5, 7, generator=g)
    obj = {
        "image": image,
        "again": image,  # the same object twice: one copy, one object after loading
        "view": (image, torch.arange(12, dtype=torch.int64).view(3, 4).t()),  # non-contiguous
        "bits": torch.rand(9, generator=g) > 0.5,
        "bytes": torch.randint(0, 255, (4, 32), dtype=torch.uint8, generator=g),
        "double": torch.randn(6, 3, dtype=torch.float64, generator=g),
        "empty": torch.zeros(0, 2),
        "scalar": torch.tensor(2.5),
        "plain": [1, "two", 3.0],
    }
    buf = np.zeros(1 << 16, dtype=np.uint8)
    back = loads(dumps(obj, buf), buf)
    for key in ("image", "bits", "bytes", "double", "empty", "scalar"):
        assert back[key].dtype == obj[key].dtype and torch.equal(back[key], obj[key]), key
    assert torch.equal(back["view"][1], obj["view"][1]) and back["plain"] == obj["plain"]
    assert back["again"] is back["image"] and back["view"][0] is back["image"]
    buf[:] = 0  # the slot is reused for the next frame: what was loaded must not change
    assert torch.equal(back["image"], image) and torch.equal(back["double"], obj["double"])


def test_views_of_one_storage_travel_once_and_stay_views_of_it():
    # A frame's image and the views its payload holds (a batch dimension, every 2nd pixel, a
    # reinterpretation of its bits): the storage's bytes are written once, and after loading the
    # views share memory as in the writer.
    image = torch.rand(3, 48, 64, generator=torch.Generator().manual_seed(1))
    obj = {"image": image, "batch": image[None], "strided": image[:, ::2, ::2], "bits": image.view(torch.int32),
           "row": image[1]}
    buf = np.zeros(1 << 16, dtype=np.uint8)
    pickler = _SlotPickler(io.BytesIO(), buf)
    pickler.dump(obj)
    assert pickler.used == image.numel() * 4  # one storage
    back = loads(dumps(obj, buf), buf)
    for key, value in obj.items():
        assert back[key].dtype == value.dtype and back[key].stride() == value.stride() and torch.equal(back[key], value), key
    ptr = back["image"].untyped_storage().data_ptr()
    assert all(back[k].untyped_storage().data_ptr() == ptr for k in obj)
    back["image"][0, 0, 0] = -1.0  # they alias as in the writer
    assert float(back["batch"][0, 0, 0, 0]) == -1.0 and float(back["strided"][0, 0, 0]) == -1.0


def test_a_small_view_of_a_large_storage_travels_alone():
    big = torch.randn(64, 1000)
    row = big[3]  # a row of a large batch: sent as its own 4 kB, not the batch's 256 kB
    buf = np.zeros(1 << 16, dtype=np.uint8)
    pickler = _SlotPickler(io.BytesIO(), buf)
    pickler.dump(row)
    assert pickler.used == 4000
    back = loads(dumps(row, buf), buf)
    assert torch.equal(back, row) and back.is_contiguous()


def test_conjugate_views_keep_their_values():
    z = torch.complex(torch.randn(5), torch.randn(5))
    buf = np.zeros(1 << 12, dtype=np.uint8)
    back = loads(dumps((z, z.conj()), buf), buf)
    assert torch.equal(back[0], z) and torch.equal(back[1].resolve_conj(), z.conj().resolve_conj())


def test_a_tensor_larger_than_the_slot_travels_inside_the_pickle():
    big, small = torch.randn(1000), torch.randn(10)
    buf = np.zeros(256, dtype=np.uint8)
    back = loads(dumps((big, small), buf), buf)
    assert torch.equal(back[0], big) and torch.equal(back[1], small)


class _Recorder:
    """A system stand-in that prepares in the child: the payload says which process made it."""

    prepares_ahead = True
    prepares_ahead_in_process = True

    def __init__(self, fail_at: int | None = None):
        self.accepted: dict[int, tuple] = {}
        self.fail_at = fail_at

    def ahead_payload(self, frame):
        if frame.index == self.fail_at:
            raise RuntimeError("preparation failed")
        return (os.getpid(), frame.rgb.mean()), {"stage": 1.0}

    def accept_ahead(self, frame, payload, stage_ms):
        self.accepted[frame.index] = (frame, payload, stage_ms)

    def prepare_ahead(self, frame):  # pragma: no cover - the thread path, not taken here
        raise AssertionError("prepared on a thread")


def test_every_frame_comes_out_in_order_with_its_payload_made_in_a_child_process():
    rec = _Recorder()
    seen = []
    for frame in AheadFrames(rec, _frames(7)):
        got, payload, stage_ms = rec.accepted[frame.index]
        assert got is frame, "the payload must belong to the very frame handed out"
        assert payload[0] != os.getpid() and torch.equal(payload[1], frame.rgb.mean()) and stage_ms == {"stage": 1.0}
        seen.append(frame.index)
    assert seen == list(range(7))


def test_a_read_error_in_the_child_is_raised_in_the_frames_place():
    got = []
    with pytest.raises(ValueError, match="frame 3: unreadable"):
        for frame in AheadFrames(_Recorder(), _frames(6, fail_at=3)):
            got.append(frame.index)
    assert got == [0, 1, 2]


def test_a_failed_preparation_hands_the_frame_out_unprepared():
    rec = _Recorder(fail_at=2)
    assert [f.index for f in AheadFrames(rec, _frames(4))] == [0, 1, 2, 3]
    assert sorted(rec.accepted) == [0, 1, 3]


def _prepared_where(queue):
    rec = _Recorder()
    rec.prepares_ahead_in_process = True
    rec.prepare_ahead = lambda frame: rec.accepted.setdefault(frame.index, (frame, "thread", {}))
    frames = [f.index for f in AheadFrames(rec, _frames(3))]
    queue.put((frames, sorted({"thread" if p == "thread" else "process" for _, p, _ in rec.accepted.values()})))


def test_a_daemonic_process_which_may_have_no_children_prepares_on_the_thread():
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_prepared_where, args=(queue,), daemon=True)
    child.start()
    frames, where = queue.get(timeout=60)
    child.join()
    assert frames == [0, 1, 2] and where == ["thread"]
    assert ahead_process.available()  # here, a process that may have children


def _gcslam_in_child(queue):
    seq = generate_sequence(SyntheticConfig(frames=12, trajectory="orbit", seed=5, **SMALL))
    system = GCSlam(GCSlamConfig())
    result = run_sequence(system, seq)
    queue.put((result.frames_processed, result.output.metrics.get("background"), system.prepares_ahead_in_process))


def test_gcslam_runs_in_a_daemonic_process_on_threads():
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_gcslam_in_child, args=(queue,), daemon=True)
    child.start()
    frames, background, wants_process = queue.get(timeout=120)
    child.join()
    # It asks for both processes (the defaults) and gets the threads, since it may have no children.
    assert frames == 12 and background == "thread" and wants_process


def test_close_stops_the_child_process():
    ahead = AheadFrames(_Recorder(), _frames(50))
    next(ahead)
    process = ahead._process.process
    ahead.close()
    assert not process.is_alive()
    with pytest.raises(StopIteration):
        next(ahead)


@pytest.mark.parametrize("frontend", ["sparse", "dense"])
def test_gcslam_gives_the_same_trajectory_prepared_in_a_process_on_a_thread_and_inline(frontend):
    seq = generate_sequence(SyntheticConfig(frames=24, trajectory="orbit", seed=5, **SMALL))
    runs = {}
    for where in ("process", "thread", "inline"):
        cfg = {"frontend": frontend, "threaded": False, "prepare_ahead": where != "inline",
               "prepare_ahead_in": "thread" if where == "inline" else where}
        system = GCSlam(config_from_dict(GCSlamConfig, cfg))
        accepted = []
        original = system.accept_ahead
        system.accept_ahead = lambda frame, payload, ms: (accepted.append(frame.index), original(frame, payload, ms))
        runs[where] = run_sequence(system, seq)
        assert len(accepted) == (len(seq) if where != "inline" else 0), where
        assert system.prepares_ahead_in_process == (where == "process")
    for where in ("thread", "inline"):
        assert torch.equal(runs["process"].output.T_wc, runs[where].output.T_wc), where
        assert torch.equal(runs["process"].output.keyframe_indices, runs[where].output.keyframe_indices), where
    stage = "orb_extraction" if frontend == "sparse" else "dense_preparation"
    assert runs["process"].output.stage_ms[stage] > 0


def test_prepare_ahead_in_is_checked():
    with pytest.raises(ConfigError, match="prepare_ahead_in"):
        config_from_dict(GCSlamConfig, {"prepare_ahead_in": "gpu"})


def test_frames_the_childs_reading_skipped_are_counted_as_in_this_process(tmp_path, shared_data):
    import cv2

    from torchslam.data import TUMSequence

    seq = copy_tum_frames(shared_data / "tum_fr1_xyz", tmp_path / "tum_fr1_xyz", 9)
    frames = TUMSequence(seq)
    depth, rgb = frames.depth_paths[3], frames.rgb_paths[5]
    cv2.imwrite(str(depth), (cv2.imread(str(depth), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))  # 8-bit depth
    cv2.imwrite(str(rgb), cv2.resize(cv2.imread(str(rgb)), (320, 240)))  # a resized colour image
    metrics = {}
    for where in ("process", "thread"):
        out = tmp_path / f"run-{where}"
        args = ["run", "--system", "gcslam", "--data", str(seq), "--out", str(out), "--no-progress", "--no-tensorboard",
                "--set", f"prepare_ahead_in={where}"]
        assert main(args) == 0
        metrics[where] = json.loads((out / "metrics.json").read_text())
    n = len(frames)
    for m in metrics.values():
        assert m["processed_frames"] == n - 2 and m["skipped_frames"] == 2
        assert [s["index"] for s in m["skipped"]] == [3, 5]
    assert metrics["process"]["skipped"] == metrics["thread"]["skipped"]
    assert metrics["process"]["ate_rmse_m"] == metrics["thread"]["ate_rmse_m"]


@pytest.mark.parametrize("stride", [1, 2])  # 2: the strided clouds of the nislam_fast(er) presets
def test_nislam_gives_the_same_trajectory_prepared_in_a_process_as_on_a_thread(stride):
    from torchslam.systems.nislam import NISlam, NISlamConfig

    seq = generate_sequence(SyntheticConfig(frames=30, trajectory="orbit", seed=6, **SMALL))
    out = {}
    for where in ("process", "thread"):
        system = NISlam(config_from_dict(NISlamConfig, {"prepare_ahead_in": where, "pixel_stride": stride}))
        out[where] = run_sequence(system, seq).output
        assert system.prepares_ahead_in_process == (where == "process")
        assert out[where].stage_ms["backproject"] > 0
    assert torch.equal(out["process"].T_wc, out["thread"].T_wc)
    assert torch.equal(out["process"].keyframe_indices, out["thread"].keyframe_indices)
    with pytest.raises(ConfigError, match="prepare_ahead_in"):
        config_from_dict(NISlamConfig, {"prepare_ahead_in": "elsewhere"})


_PARALLEL_PARENT = """
import torch
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.systems import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig

torch.set_num_threads(2)
a = torch.randn(64, 128, 128, dtype=torch.float64)
(a @ a).sum()  # a parallel region: OpenMP's pool now has workers in this process
seq = generate_sequence(SyntheticConfig(frames=6, trajectory="orbit", seed=5, width=160, height=120))
system = GCSlam(GCSlamConfig(threaded=False))
result = run_sequence(system, seq)
assert system.prepares_ahead_in_process
print("frames", result.frames_processed, torch.get_num_threads())
"""


def test_a_parent_on_several_threads_that_ran_a_parallel_region_does_not_hang_its_child():
    """OpenMP's pool does not survive a fork: a child on the parent's intra-op count waited forever
    in libgomp (``torchslam run --system gcslam --threads 2``). The child runs on one thread."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    try:
        done = subprocess.run([sys.executable, "-c", _PARALLEL_PARENT], capture_output=True, text=True, timeout=120, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail("GC-SLAM with its frames prepared in a child process hung after a parallel region on 2 threads")
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-3:] == ["frames", "6", "2"], done.stdout
