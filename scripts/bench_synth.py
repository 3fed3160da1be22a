"""Benchmark the synthetic RGB-D-inertial generator.

Measures, for 640 x 480 frames by default:

* render frames/s of the batched ray caster alone, for several batch sizes and torch thread
  counts (the renderer's device: CPU here, CUDA with ``--device cuda``);
* sequence frames/s through ``SyntheticSequence.render``, with and without the Kinect-like depth
  noise (the noise draws one generator per frame);
* the wall time of a whole default sequence: construction (scene, trajectory, IMU, AHRS) plus
  rendering every frame;
* the attitude filter on 10^4 IMU samples (milliseconds).

Every figure is the best and the median of ``--repeat`` runs; timings on a machine shared with
other jobs vary a lot, and the best run is the closest to what the code can do. Writes
``scripts/results/bench_synth.json`` and prints a markdown table. Usage::

    python scripts/bench_synth.py [--frames 300] [--batch 1 4 8 16] [--threads 1 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from _bench import RESULTS, load_average, sync, time_calls
from torchslam.data import SyntheticConfig, generate_sequence
from torchslam.imu import ImuData, ahrs_attitude
from torchslam.environment import cpu_model as _cpu_model


def _load() -> list[float] | None:
    load = load_average()
    return None if load is None else [round(x, 2) for x in load]


def _stats(seconds: list[float], frames: int) -> dict:
    return {
        "fps_best": frames / min(seconds),
        "fps_median": frames / statistics.median(seconds),
        "seconds": seconds,
    }


def bench_render(seq, batch: int, repeat: int, device: str) -> dict:
    """Frames/s of the ray caster alone over ``repeat`` batches of distinct poses."""
    n = len(seq)
    times = []
    seq.renderer.render(seq.groundtruth.T_wc[:batch])  # warm-up (allocator, caches)
    for r in range(repeat):
        idx = [(r * batch + k) % n for k in range(batch)]
        T = seq.groundtruth.T_wc[idx]
        sync(device)
        t0 = time.perf_counter()
        seq.renderer.render(T)
        sync(device)
        times.append(time.perf_counter() - t0)
    return _stats(times, batch)


def bench_sequence_render(seq, batch: int, repeat: int, device: str) -> dict:
    """Frames/s through SyntheticSequence.render (rendering plus the configured depth noise)."""
    n = len(seq)
    seq.render(range(batch))
    times = []
    for r in range(repeat):
        idx = [(r * batch + k) % n for k in range(batch)]
        sync(device)
        t0 = time.perf_counter()
        seq.render(idx)
        sync(device)
        times.append(time.perf_counter() - t0)
    return _stats(times, batch)


def bench_full_sequence(cfg: SyntheticConfig, device: str) -> dict:
    """Wall time to build a sequence and render all of its frames (as iteration does)."""
    t0 = time.perf_counter()
    seq = generate_sequence(cfg, device=device)
    t_build = time.perf_counter() - t0
    t1 = time.perf_counter()
    for start in range(0, len(seq), cfg.batch_size):
        seq.render(range(start, min(len(seq), start + cfg.batch_size)))
    sync(device)
    t_render = time.perf_counter() - t1
    return {
        "frames": len(seq),
        "build_s": t_build,
        "render_s": t_render,
        "total_s": t_build + t_render,
        "fps_end_to_end": len(seq) / (t_build + t_render),
    }


def bench_ahrs(samples: int, repeat: int) -> dict:
    g = torch.Generator().manual_seed(0)
    t = torch.arange(samples, dtype=torch.float64) / 200
    gyro = 0.3 * torch.randn(samples, 3, generator=g, dtype=torch.float64)
    accel = torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64) + 0.1 * torch.randn(samples, 3, generator=g, dtype=torch.float64)
    imu = ImuData(t, gyro, accel)
    t = time_calls(lambda: ahrs_attitude(imu), repeat)
    return {"samples": samples, "ms_best": 1e3 * t.best, "ms_median": 1e3 * t.median}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 4, 8, 16])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_synth.json")
    args = parser.parse_args()

    base = dict(frames=args.frames, width=args.width, height=args.height)
    results: dict = {
        "machine": {
            "nproc": os.cpu_count(),
            "cpu": _cpu_model(),
            "torch": torch.__version__,
            "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
            "load_average_start": _load(),
        },
        "config": {**base, "repeat": args.repeat},
        "render": [],
        "sequence": [],
        "full_sequence": [],
    }
    threads_before = torch.get_num_threads()
    clean = generate_sequence(SyntheticConfig(**base, depth_noise=False), device=args.device)
    noisy = generate_sequence(SyntheticConfig(**base, depth_noise=True), device=args.device)
    for threads in args.threads:
        torch.set_num_threads(threads)
        for batch in args.batch:
            r = bench_render(clean, batch, args.repeat, args.device)
            results["render"].append({"threads": threads, "batch": batch, **r})
        for name, seq in (("noise off", clean), ("noise on", noisy)):
            r = bench_sequence_render(seq, 8, args.repeat, args.device)
            results["sequence"].append({"threads": threads, "batch": 8, "depth_noise": name, **r})
        for noise in (False, True):
            r = bench_full_sequence(SyntheticConfig(**base, depth_noise=noise), args.device)
            results["full_sequence"].append({"threads": threads, "depth_noise": noise, **r})
    torch.set_num_threads(1)
    results["ahrs"] = bench_ahrs(10_000, max(3, args.repeat))
    torch.set_num_threads(threads_before)
    results["machine"]["load_average_end"] = _load()

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    m = results["machine"]
    print(f"machine: {m['nproc']} CPUs, {m['cpu']}, torch {m['torch']}, device {m['device']}, "
          f"load average {m['load_average_start']} -> {m['load_average_end']}")
    print(f"\n{args.width}x{args.height} ray casting (renderer only)\n")
    print("| threads | batch | frames/s best | frames/s median |")
    print("|---:|---:|---:|---:|")
    for r in results["render"]:
        print(f"| {r['threads']} | {r['batch']} | {r['fps_best']:.1f} | {r['fps_median']:.1f} |")
    print("\nSyntheticSequence.render, batch 8\n")
    print("| threads | depth noise | frames/s best | frames/s median |")
    print("|---:|---|---:|---:|")
    for r in results["sequence"]:
        print(f"| {r['threads']} | {r['depth_noise']} | {r['fps_best']:.1f} | {r['fps_median']:.1f} |")
    print(f"\nwhole {args.frames}-frame sequence (build + render every frame)\n")
    print("| threads | depth noise | build s | render s | total s | frames/s |")
    print("|---:|---|---:|---:|---:|---:|")
    for r in results["full_sequence"]:
        print(f"| {r['threads']} | {'on' if r['depth_noise'] else 'off'} | {r['build_s']:.2f} | {r['render_s']:.2f} | "
              f"{r['total_s']:.2f} | {r['fps_end_to_end']:.1f} |")
    a = results["ahrs"]
    print(f"\nattitude filter, {a['samples']} IMU samples, 1 thread: {a['ms_best']:.1f} ms best, {a['ms_median']:.1f} ms median")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
