"""Benchmark Hamming matching of ORB descriptors: torch kernels against OpenCV, and MILD queries.

Descriptors are 2000 ORB features from each of two TUM fr1/xyz frames (random descriptors when
the data folder is missing). Timed, each as the best and the median of ``--repeat`` runs:

* the full (2000, 2000) distance matrix with the torch kernels ``swar`` (int64 SWAR popcount),
  ``lut`` (byte lookup table) and ``matmul`` (±1 GEMM);
* nearest-neighbour matching: ``match_descriptors`` with the torch backend (each kernel), with
  the OpenCV backend (``cv2.batchDistance``), the int8 GEMM backend (``torch._int_mm``, the CPU
  default), and OpenCV's ``BFMatcher(NORM_HAMMING).match``;
* the same on CUDA when a GPU is present (the path the torch backend exists for);
* MILD: inserting real keyframes (every 5th frame of the three sequences) one by one, and
  querying the full database with one frame of each sequence.

Timings are taken with torch at its default thread count and again with one thread. Writes
``scripts/results/bench_matching.json`` and prints a markdown table. Usage::

    python scripts/bench_matching.py [--data DIR] [--repeat 7] [--features 2000]
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

from _bench import RESULTS, data_root, load_average, time_calls
from torchslam.data import TUMSequence
from torchslam.features import ORBConfig, extract_orb, hamming_distance, match_descriptors
from torchslam.loop import MILDConfig, MILDDatabase
from torchslam.environment import cpu_model as _cpu_model
from torchslam.features.matching import cpu_auto_backend


def _time(fn, repeat: int, device: str = "cpu") -> dict:
    t = time_calls(fn, repeat, device)
    return {"best_ms": t.best * 1e3, "median_ms": t.median * 1e3}


def _descriptors(data: Path, n_features: int) -> tuple[torch.Tensor, torch.Tensor, str]:
    seq_dir = data / "tum_fr1_xyz"
    if (seq_dir / "rgb.txt").is_file():
        seq = TUMSequence(seq_dir)
        cfg = ORBConfig(n_features=n_features)
        f1, f2 = extract_orb(seq[0].rgb, cfg), extract_orb(seq[10].rgb, cfg)
        return f1.descriptors, f2.descriptors, "ORB of tum_fr1_xyz frames 0 and 10"
    gen = torch.Generator().manual_seed(0)
    d1 = torch.randint(0, 256, (n_features, 32), dtype=torch.uint8, generator=gen)
    d2 = torch.randint(0, 256, (n_features, 32), dtype=torch.uint8, generator=gen)
    return d1, d2, "uniform random (no data folder)"


def _matching_rows(d1, d2, repeat: int, device: str) -> list[dict]:
    a, b = d1.to(device), d2.to(device)
    rows = []
    for kernel in ("swar", "lut", "matmul"):
        rows.append({"task": "distance matrix", "impl": f"torch {kernel}", "device": device,
                     **_time(lambda: hamming_distance(a, b, kernel), repeat, device)})
    for kernel in ("swar", "matmul"):
        rows.append({"task": "nearest neighbour", "impl": f"torch {kernel}", "device": device,
                     **_time(lambda: match_descriptors(a, b, backend="torch", kernel=kernel), repeat, device)})
    if device == "cpu":
        an, bn = d1.numpy(), d2.numpy()
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        rows.append({"task": "nearest neighbour", "impl": "opencv BFMatcher.match", "device": "cpu",
                     **_time(lambda: bf.match(an, bn), repeat)})
        rows.append({"task": "nearest neighbour", "impl": "opencv backend (batchDistance)", "device": "cpu",
                     **_time(lambda: match_descriptors(d1, d2, backend="opencv"), repeat)})
        rows.append({"task": "nearest neighbour", "impl": "int8 backend (torch._int_mm)", "device": "cpu",
                     **_time(lambda: match_descriptors(d1, d2, backend="int8"), repeat)})
        rows.append({"task": "nearest neighbour", "impl": "auto backend", "device": "cpu",
                     **_time(lambda: match_descriptors(d1, d2), repeat)})
    return rows


def _mild_inputs(data: Path, n_features: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Real keyframes (every 5th frame of every sequence) and one query frame per sequence."""
    cfg = ORBConfig(n_features=n_features)
    keyframes, queries = [], []
    for name in ("tum_fr1_xyz", "7scenes_redkitchen", "hololens_dvmvs"):
        if not (data / name / "rgb.txt").is_file():
            continue
        seq = TUMSequence(data / name)
        for i in range(0, len(seq), 5):
            keyframes.append(extract_orb(seq[i].rgb, cfg).descriptors)
        queries.append(extract_orb(seq[2].rgb, cfg).descriptors)
    return keyframes, queries


def _mild_rows(keyframes, queries, repeat: int) -> list[dict]:
    """Time inserting every keyframe into a fresh database, then queries against all of them."""
    if not keyframes:
        return []
    db = MILDDatabase(MILDConfig())
    add_ms = []
    for i, desc in enumerate(keyframes):
        t0 = time.perf_counter()
        db.add(i, desc)
        add_ms.append((time.perf_counter() - t0) * 1e3)
    timing = _time(lambda: [db.query(q) for q in queries], repeat)
    per_query = {k: v / len(queries) for k, v in timing.items()}
    return [
        {"task": f"MILD add, per keyframe ({len(keyframes)} keyframes)", "impl": "torch", "device": "cpu",
         "best_ms": min(add_ms), "median_ms": statistics.median(add_ms), "mean_ms": statistics.fmean(add_ms)},
        {"task": f"MILD query ({db.num_descriptors} stored descriptors, {db.num_levels} levels)",
         "impl": "torch", "device": "cpu", **per_query},
    ]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root())
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per setting (best and median reported)")
    parser.add_argument("--features", type=int, default=2000, help="ORB features per frame")
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_matching.json")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")

    machine = {
        "cpu_model": _cpu_model(),
        "nproc": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_average_at_start": load_average(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "auto_backend_cpu": cpu_auto_backend().value,
    }
    d1, d2, source = _descriptors(args.data, args.features)
    default_threads = torch.get_num_threads()
    keyframes, queries = _mild_inputs(args.data, args.features)
    rows = []
    for threads in sorted({default_threads, 1}, reverse=True):
        torch.set_num_threads(threads)
        for row in _matching_rows(d1, d2, args.repeat, "cpu") + _mild_rows(keyframes, queries, args.repeat):
            rows.append({**row, "torch_threads": threads})
    torch.set_num_threads(default_threads)
    if torch.cuda.is_available():
        rows += [{**r, "torch_threads": None} for r in _matching_rows(d1, d2, args.repeat, "cuda")]
    machine["load_average_at_end"] = load_average()

    report = {
        "descriptors": {"source": source, "k1": int(d1.shape[0]), "k2": int(d2.shape[0])},
        "machine": machine,
        "repeat": args.repeat,
        "note": "CPU timings on a shared machine under other load are contended; compare rows of one run only",
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")

    print(f"\nmachine: {machine['cpu_model']}, {machine['cpus_usable']} usable CPUs, load {machine['load_average_at_start']}"
          f"; CUDA: {machine['cuda'] or 'none'}")
    print(f"descriptors: {source}, {d1.shape[0]} x {d2.shape[0]}\n")
    print("| task | implementation | device | torch threads | best ms | median ms |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['task']} | {r['impl']} | {r['device']} | {r['torch_threads'] or '-'} "
              f"| {r['best_ms']:.2f} | {r['median_ms']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
