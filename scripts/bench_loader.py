"""Benchmark the TUM-format loader: decode frames/s with and without background prefetch.

For each sequence and each prefetch depth (0, 2, 4 by default) the whole sequence is iterated
with three kinds of consumer:

* ``none``: the consumer does nothing, so this is the pure decode rate;
* ``spin``: the consumer busy-waits ``--work-ms`` per frame in a loop that releases the GIL
  between clock reads, like torch kernels do, so decoding in the prefetch thread can overlap it;
* ``spin-gil``: the same busy-wait as a pure Python loop that holds the GIL, the worst case for a
  thread-based prefetch (the decoder thread only gets the GIL at the interpreter's switch interval).

Each setting runs with each decoder of ``--decoders``: ``fast`` (the loader's default: PNGs on
``torchslam.data.png``'s ISA-L path where they qualify, else OpenCV) and ``opencv`` (OpenCV for
every image, as before that path existed), so both are measured in the same run.

Writes ``scripts/results/bench_loader.json`` and prints a markdown table. Usage::

    python scripts/bench_loader.py [--data DIR] [--repeat 3] [--work-ms 10] [--max-frames N] [--decoders fast,opencv]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import cv2
import torch

from _bench import RESULTS, data_root, load_average
from torchslam.data import TUMSequence
from torchslam.environment import cpu_model as _cpu_model

SEQUENCES = ("tum_fr1_xyz", "7scenes_redkitchen", "hololens_dvmvs")


def _spin_nogil(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        time.sleep(0)  # releases the GIL, stays on the CPU


def _spin_gil(seconds: float) -> None:
    end = time.perf_counter() + seconds
    x = 0
    while time.perf_counter() < end:
        for _ in range(100):
            x += 1


WORK = {"none": None, "spin": _spin_nogil, "spin-gil": _spin_gil}


def _one_pass(seq: TUMSequence, work, work_s: float) -> tuple[float, int]:
    start = time.perf_counter()
    n = 0
    for frame in seq:
        n += 1
        if work is not None:
            work(work_s)
    if n != len(seq):
        raise RuntimeError(f"{seq.name}: iterated {n} of {len(seq)} frames (skipped: {seq.skipped})")
    return time.perf_counter() - start, n


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=data_root(),
                        help="folder holding the sequences (default $TORCHSLAM_DATA or ../shared/data)")
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES), help="sequence folder names under --data")
    parser.add_argument("--prefetch", nargs="+", type=int, default=[0, 2, 4], help="prefetch depths to compare")
    parser.add_argument("--work", nargs="+", choices=list(WORK), default=list(WORK), help="consumer kinds")
    parser.add_argument("--work-ms", type=float, default=10.0, help="simulated compute per frame, milliseconds")
    parser.add_argument("--repeat", type=int, default=3, help="passes per setting; the best and median are reported")
    parser.add_argument("--max-frames", type=int, default=None, help="use only the first N frames of each sequence")
    parser.add_argument("--decoders", default="fast,opencv",
                        help="comma-separated: fast (the default loader) and/or opencv (OpenCV for every image)")
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_loader.json")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    decoders = [d.strip() for d in args.decoders.split(",") if d.strip()]
    if not decoders or any(d not in ("fast", "opencv") for d in decoders):
        parser.error(f"--decoders: expected fast and/or opencv, got {args.decoders!r}")

    machine = {
        "nproc": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu_model": _cpu_model(),
        "load_average_at_start": load_average(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "platform": platform.platform(),
    }
    results = []
    for name in args.sequences:
        root = args.data / name
        if not (root / "rgb.txt").is_file():
            print(f"skipping {name}: {root} has no rgb.txt")
            continue
        _one_pass(TUMSequence(root, end=args.max_frames), None, 0.0)  # warm the page cache
        for work_name in args.work:
            for prefetch in args.prefetch:
                seqs = {d: TUMSequence(root, prefetch=prefetch, end=args.max_frames, fast_png=d == "fast") for d in decoders}
                times: dict[str, list[float]] = {d: [] for d in decoders}
                for _ in range(args.repeat):
                    for d in decoders:  # alternating, so drifting load hits both alike
                        seconds, n = _one_pass(seqs[d], WORK[work_name], args.work_ms / 1000.0)
                        times[d].append(seconds)
                for d in decoders:
                    seq = seqs[d]
                    results.append({
                        "sequence": name,
                        "frames": n,
                        "image_size": [seq.camera.width, seq.camera.height],
                        "decoder": d,
                        "fast_path_used": seq.fast_png_streams,
                        "work": work_name,
                        "work_ms": 0.0 if work_name == "none" else args.work_ms,
                        "prefetch": prefetch,
                        "seconds": times[d],
                        "fps_best": n / min(times[d]),
                        "fps_median": n / statistics.median(times[d]),
                    })
                    print(f"{name:20s} {d:6s} work={work_name:8s} prefetch={prefetch}: "
                          f"{results[-1]['fps_median']:7.1f} frames/s (median)")

    report = {
        "benchmark": "TUMSequence iteration frames/s (decode to float tensors), prefetch thread vs none, fast PNG path vs OpenCV",
        "machine": machine,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "note": "timings on a shared machine under other load are contended; compare rows from one run only",
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")

    print(f"\nmachine: {machine['cpu_model']}, {machine['cpus_usable']} usable CPUs; frames/s, median of {args.repeat}\n")
    header = "| sequence | frames | decoder | consumer | " + " | ".join(f"prefetch {p}" for p in args.prefetch) + " |"
    print(header)
    print("|" + "---|" * (4 + len(args.prefetch)))
    rows: dict[tuple[str, str, str], dict[int, dict]] = {}
    for r in results:
        rows.setdefault((r["sequence"], r["decoder"], r["work"]), {})[r["prefetch"]] = r
    for (name, decoder, work_name), by_p in rows.items():
        any_r = next(iter(by_p.values()))
        label = "decode only" if work_name == "none" else f"{work_name} {args.work_ms:g} ms"
        if decoder == "fast" and not any(any_r["fast_path_used"].values()):
            decoder = "fast (declined: OpenCV)"
        cells = " | ".join(f"{by_p[p]['fps_median']:.1f}" if p in by_p else "-" for p in args.prefetch)
        print(f"| {name} | {any_r['frames']} | {decoder} | {label} | {cells} |")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
