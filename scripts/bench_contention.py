"""What slows a tracking step down when other work of the same run shares the two cores.

    python scripts/bench_contention.py [--sequence tum_fr1_xyz] [--seconds 2] [--out PATH]

The measured step is GC-SLAM's sparse tracking registration (guided matching, isometry filter,
RANSAC, refinement) of two frames of the sequence, timed alone and then beside one worker that
repeats a piece of a run's other per-frame work without pause, once on a thread of this process
(sharing the interpreter lock) and once in a forked child process (sharing only the machine).
The workers: ``orb`` (OpenCV's ORB on a grey image, which releases the lock), ``features``
(``frame_features``: grey conversion, ORB and the keypoints lifted to 3-D, as the ahead thread
runs it), ``decode`` (one frame read, decoded and converted, as the loader thread runs it),
``convert`` (only the colour and depth conversion to float, NumPy), and ``python`` (a pure-Python
loop, thread only: the step waits for the interpreter lock at each release). The ratio
beside / alone is what the worker costs the step; a ratio that a thread shows and a process does
not is the interpreter lock's, one both show is the machine's (caches, memory bandwidth). The
worker's own rate is reported too. One torch and one OpenCV thread. Results:
``scripts/results/bench_contention.json``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from _bench import RESULTS, data_root, load_average, write_json

from torchslam.environment import environment_info

WORKERS = ("orb", "features", "decode", "convert", "python")


def _make(sequence: str):
    from torchslam.data.tum import TUMSequence
    from torchslam.features import orb as O
    from torchslam.registration import sparse as S

    seq = TUMSequence(data_root() / sequence, prefetch=0)
    cam = seq.camera
    fi, fj = seq[40], seq[42]
    orb_cfg = O.ORBConfig(n_features=2000)
    F = [S.frame_features(f.rgb, f.depth, cam, orb_cfg) for f in (fi, fj)]
    cfg = S.SparseConfig()
    T = S.register_sparse_batch([F[0]], [F[1]], cfg).T_ij.clone()

    def step() -> None:
        S.register_sparse_batch([F[0]], [F[1]], cfg, T_pred=T, focal=cam.fx)

    orb = O._make_orb(orb_cfg)
    grey = O.rgb_to_grey_u8(fi.rgb[None])[0].numpy()
    rgb8 = np.ascontiguousarray((fi.rgb.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
    raw = (fi.depth[0].numpy() * seq.depth_scale).round().astype(np.uint16)

    def convert() -> None:
        out = np.empty((3,) + rgb8.shape[:2], dtype=np.float32)
        for channel, plane in zip(out, cv2.split(rgb8)):
            np.divide(plane, np.float32(255.0), out=channel, dtype=np.float32)
        metres = raw.astype(np.float32)
        metres /= np.float32(seq.depth_scale)

    def python_loop() -> None:
        x = 0
        for k in range(20000):
            x += k

    work = {
        "orb": lambda: orb.detectAndCompute(grey, None),
        "features": lambda: S.frame_features(fj.rgb, fj.depth, cam, orb_cfg),
        "decode": lambda: seq[50],
        "convert": convert,
        "python": python_loop,
    }
    return step, work


def _timed(fn, seconds: float, max_calls: int = 100000) -> tuple[float, int]:
    """Mean milliseconds per call of ``fn`` over about ``seconds`` (at least 3 calls)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while n < 3 or (time.perf_counter() - t0 < seconds and n < max_calls):
        fn()
        n += 1
    return 1e3 * (time.perf_counter() - t0) / n, n


def _loop(fn, stop, count) -> None:
    while not stop.is_set():
        fn()
        with count.get_lock():
            count.value += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", default="tum_fr1_xyz")
    ap.add_argument("--seconds", type=float, default=2.0, help="timing window per measurement")
    ap.add_argument("--workers", default=",".join(WORKERS))
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_contention.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    step, work = _make(args.sequence)
    ctx = multiprocessing.get_context("fork")
    rows = []
    print(f"{'worker':10s} {'where':8s} {'step alone ms':>14s} {'beside ms':>10s} {'ratio':>6s} {'worker ms/call':>15s}")
    for name in args.workers.split(","):
        if name not in work:
            raise SystemExit(f"--workers: unknown worker {name!r}; choose from {', '.join(WORKERS)}")
        alone_worker, _ = _timed(work[name], min(args.seconds, 1.0))
        for where in ("thread", "process") if name != "python" else ("thread",):
            alone, _ = _timed(step, args.seconds)
            stop, count = ctx.Event(), ctx.Value("q", 0)
            if where == "thread":
                runner = threading.Thread(target=_loop, args=(work[name], stop, count), daemon=True)
            else:
                runner = ctx.Process(target=_loop, args=(work[name], stop, count), daemon=True)
            runner.start()
            time.sleep(0.2)
            c0, t0 = count.value, time.perf_counter()
            # A pure-Python worker stalls the step for whole switch intervals: a few calls suffice.
            beside, calls = _timed(step, args.seconds, max_calls=5 if name == "python" else 100000)
            worker_ms = 1e3 * (time.perf_counter() - t0) / max(count.value - c0, 1)
            stop.set()
            runner.join()
            row = {"worker": name, "where": where, "step_alone_ms": alone, "step_beside_ms": beside, "ratio": beside / alone,
                   "step_calls": calls, "worker_alone_ms": alone_worker, "worker_beside_ms": worker_ms}
            rows.append(row)
            print(f"{name:10s} {where:8s} {alone:14.2f} {beside:10.2f} {beside / alone:6.2f} {worker_ms:15.2f}")
    write_json(args.out, {
        "machine": {**environment_info(), "load_average": load_average()},
        "threads": {"torch": 1, "opencv": 1},
        "sequence": args.sequence,
        "step": "sparse tracking registration, frames 40 and 42, guided",
        "seconds": args.seconds,
        "rows": rows,
    })


if __name__ == "__main__":
    main()
