"""Benchmark NI-SLAM on many sequences: lockstep (``run_lockstep``) against one sequence after another.

For each group size B, the same B sequences are run three ways in the same process, one right
after the other: one after another with ``run_sequence`` (the unbatched baseline), in lockstep
with the default split into batched calls (``max_batch=None``: ``default_max_batch``, which on
the CPU depends on the orthographic image size) and in lockstep as one ``(B, ...)`` batch (``max_batch=B``). Throughput is
the frames of all B sequences over the group's wall-clock time. Frames are rendered into memory
before any timing (decode and rendering are not measured); the full system runs, keyframes and
loop closure included.

The B sequences are drawn from a pool of synthetic sequences (four trajectories x two seeds);
sequence b plays pool item ``b % P`` from frame ``b // P`` on, so no two sequences of a group
feed the same frame in the same step.

Writes ``scripts/results/bench_batch.json`` and ``bench_batch.png`` and prints a markdown table.

    python scripts/bench_batch.py              # setups full and small, B = 1 ... 64, 20 frames each
    python scripts/bench_batch.py --quick      # smoke run (setup tiny)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from _bench import RESULTS, sync
from torchslam.data.frame import Frame
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.environment import environment_info
from torchslam.systems import run_sequence
from torchslam.systems.lockstep import default_max_batch, run_lockstep
from torchslam.systems.nislam import NISlam, NISlamConfig

POOL = [(t, s) for s in (0, 1) for t in ("orbit", "translate", "loop", "handheld")]


class InMemorySequence:
    """Frames held in memory (a ``Sequence``): playing it costs no decoding or rendering."""

    def __init__(self, source, start: int, frames: int, device: str):
        self.name = f"{source.name}-from{start}"
        self.camera = source.camera
        self.groundtruth = source.groundtruth
        self.attitude = source.attitude
        self.timestamps = source.timestamps[start : start + frames]
        self.frames = [
            dataclasses.replace(f, index=k, rgb=f.rgb.to(device), depth=f.depth.to(device))
            for k, f in enumerate(source[j] for j in range(start, start + frames))
        ]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Frame:
        return self.frames[index]

    def __iter__(self):
        return iter(self.frames)


def make_group(pool: list, B: int, frames: int, device: str, cache: dict) -> list[InMemorySequence]:
    """B in-memory sequences; each (pool item, start) is rendered once and shared between group sizes."""
    group = []
    for b in range(B):
        key = (b % len(pool), b // len(pool))
        if key not in cache:
            cache[key] = InMemorySequence(pool[key[0]], key[1], frames, device)
        group.append(cache[key])
    return group


def measure(cfg: NISlamConfig, group: list, device: str, mode: str) -> dict:
    """Run ``group`` one way; frames/s over the group's wall-clock time."""
    B = len(group)
    sync(device)
    t0 = time.perf_counter()
    if mode == "sequential":
        results = [run_sequence(NISlam(cfg, device=device), seq) for seq in group]
    else:
        results = run_lockstep(cfg, group, device=device, max_batch=B if mode == "one batch" else None)
    sync(device)
    wall = time.perf_counter() - t0
    bad = [r for r in results if isinstance(r, BaseException)]
    if bad:
        raise bad[0]
    frames = sum(r.frames_processed for r in results)
    return {
        "mode": mode, "B": B, "frames": frames, "wall_s": wall, "frames_per_s": frames / wall,
        "keyframes": sum(len(r.output.keyframe_indices) for r in results),
        "T_wc": [r.output.T_wc for r in results],
    }


def run(cfg: NISlamConfig, pool: list, sizes: list[int], frames: int, device: str, repeats: int) -> list[dict]:
    """Each mode ``repeats`` times per B; the best run of each mode is kept (the machine is shared)."""
    rows = []
    cache: dict = {}
    modes = ["sequential", "lockstep", "one batch"]
    # Warm-up (allocator, cached rays): not recorded.
    measure(cfg, make_group(pool, 2, 3, device, {}), device, "lockstep")
    for B in sizes:
        group = make_group(pool, B, frames, device, cache)
        runs: dict[str, list[dict]] = {m: [] for m in modes}
        for rep in range(repeats):
            # Alternate the order so a slow spell of the machine does not always hit one mode.
            for m in modes if rep % 2 == 0 else modes[::-1]:
                runs[m].append(measure(cfg, group, device, m))
        best = {m: max(runs[m], key=lambda r: r["frames_per_s"]) for m in modes}
        median = {m: sorted(r["frames_per_s"] for r in runs[m])[len(runs[m]) // 2] for m in modes}
        ref = best["sequential"]
        for m in modes:
            r = best[m]
            dev = max(float((a - b).abs().max()) for a, b in zip(ref["T_wc"], r["T_wc"]) if len(a) == len(b))
            row = {k: v for k, v in r.items() if k != "T_wc"}
            max_batch = {"sequential": None, "lockstep": min(B, default_max_batch(cfg, device, B)), "one batch": B}[m]
            row.update(device=device, repeats=repeats, frames_per_s_median=median[m],
                       all_frames_per_s=[x["frames_per_s"] for x in runs[m]],
                       ratio_to_sequential=r["frames_per_s"] / ref["frames_per_s"],
                       ratio_to_sequential_median=median[m] / median["sequential"],
                       max_pose_difference_m=dev, max_batch=max_batch)
            rows.append(row)
            print(f"  {device} B={B:3d} {m:11s} {r['frames_per_s']:7.1f} frames/s best, {median[m]:7.1f} median  "
                  f"x{row['ratio_to_sequential']:.2f} (median x{row['ratio_to_sequential_median']:.2f}, "
                  f"max pose diff {dev:.1e} m)", flush=True)
    return rows


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    colours = dict(zip(result["setups"], ("tab:blue", "tab:orange", "tab:green")))
    for name in result["setups"]:
        for dev in sorted({r["device"] for r in result["rows"]}):
            for mode, style in (("sequential", "s--"), ("lockstep", "o-"), ("one batch", "^:")):
                rows = [r for r in result["rows"] if r["setup"] == name and r["device"] == dev and r["mode"] == mode]
                label = f"{name} {dev} {mode}"
                axes[0].plot([r["B"] for r in rows], [r["frames_per_s"] for r in rows], style, color=colours[name], label=label)
                if mode != "sequential":
                    axes[1].plot([r["B"] for r in rows], [r["ratio_to_sequential"] for r in rows], style,
                                 color=colours[name], label=label)
    axes[1].axhline(1.0, color="grey", lw=0.8)
    for ax in axes:
        ax.set_xscale("log", base=2)
        ax.set_xlabel("sequences B")
        ax.legend(fontsize=7)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("frames/s, summed over sequences")
    axes[0].set_title("NI-SLAM on B sequences")
    axes[1].set_ylabel("frames/s over sequential frames/s")
    axes[1].set_title("Lockstep over one after another, same run")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


SETUPS = {
    # name: (image width, height, orthographic height, width, group sizes B)
    "full": (640, 480, 360, 480, "1,2,4,8,16"),  # the paper's input, torchslam's default orthographic size
    "small": (320, 240, 180, 240, "1,2,4,8,16,32,64"),
    "tiny": (160, 120, 90, 120, "1,2,4"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="setup tiny, 6 frames, one repeat")
    ap.add_argument("--setups", default="full,small", help=f"comma-separated, of {sorted(SETUPS)}")
    ap.add_argument("--sizes", default=None, help="comma-separated group sizes B (default: per setup)")
    ap.add_argument("--frames", type=int, default=16, help="frames per sequence")
    ap.add_argument("--repeats", type=int, default=3, help="runs per mode and B; the best is reported")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1: the machine is shared)")
    ap.add_argument("--no-cuda", action="store_true", help="skip CUDA even where available")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    frames = 6 if args.quick else args.frames
    repeats = 1 if args.quick else args.repeats
    setups = ["tiny"] if args.quick else args.setups.split(",")
    devices = ["cpu"] + (["cuda"] if not args.no_cuda and torch.cuda.is_available() else [])
    result = {
        "machine": environment_info(), "quick": args.quick, "frames_per_sequence": frames, "repeats": repeats,
        "pool": [f"{t}-seed{s}" for t, s in POOL],
        "note": "frames pre-rendered into memory (no decode); full NI-SLAM incl. keyframes and loop closure",
        "setups": {}, "rows": [],
    }
    print(f"machine: {result['machine']}")
    sizes = {}
    for name in setups:
        width, height, oh, ow, default_sizes = SETUPS[name]
        sizes[name] = [int(b) for b in (args.sizes or default_sizes).split(",")]
        cfg = NISlamConfig()
        cfg = dataclasses.replace(cfg, min_valid_points=min(cfg.min_valid_points, width * height // 20),
                                  kcc=dataclasses.replace(cfg.kcc, ortho_height=oh, ortho_width=ow))
        result["setups"][name] = {"image": [width, height], "ortho": [ow, oh],
                                  "default_cpu_max_batch": default_max_batch(cfg, "cpu", max(sizes[name]))}
        start_max = (max(sizes[name]) - 1) // len(POOL)
        pool = [generate_sequence(SyntheticConfig(frames=frames + start_max, width=width, height=height, trajectory=t, seed=s))
                for t, s in POOL]
        print(f"{name}: {width}x{height} images, {ow}x{oh} orthographic")
        for device in devices:
            rows = run(cfg, pool, sizes[name], frames, device, repeats)
            for r in rows:
                r["setup"] = name
            result["rows"] += rows
        del pool
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = "bench_batch_quick" if args.quick else "bench_batch"
    (out / f"{stem}.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result, out / f"{stem}.png")
    print("\n| setup | device | B | sequential frames/s | lockstep frames/s (max_batch) | ratio | one batch frames/s | ratio |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name in setups:
        for dev in devices:
            for B in sizes[name]:
                got = {r["mode"]: r for r in result["rows"] if r["setup"] == name and r["device"] == dev and r["B"] == B}
                s, ls, ob = got["sequential"], got["lockstep"], got["one batch"]
                print(f"| {name} | {dev} | {B} | {s['frames_per_s']:.1f} | {ls['frames_per_s']:.1f} ({ls['max_batch']}) | "
                      f"{ls['ratio_to_sequential']:.2f} | {ob['frames_per_s']:.1f} | {ob['ratio_to_sequential']:.2f} |")


if __name__ == "__main__":
    main()
