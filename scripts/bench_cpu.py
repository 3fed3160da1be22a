"""CPU time per frame of a `torchslam run`, thread by thread, from the operating system's accounts.

    python scripts/bench_cpu.py --system gcslam --sequence tum_fr1_xyz [--frames 60,204] [--rounds 3] \
        [--set frontend=dense] [--out scripts/results/bench_cpu.json]

Each round runs ``torchslam run`` twice in fresh processes, on the first A and the first B frames
(``--frames A,B``), while a sampler reads every thread's CPU time (user + system) of the run's
process and its children from ``/proc`` every 20 ms. A thread's CPU per frame is its time in the
B-frame run minus its time in the A-frame run, divided by B - A, so the interpreter's start-up,
imports, ``start`` and ``finish`` cancel. Threads are grouped by the names torchslam gives them
(``threads.name_os_thread``: ``tslam-prepare``, ``tslam-decode``, ``tslam-ahead``,
``tslam-optimizer`` ...); the run's main thread, which tracks, is ``main (tracking)``. Reports the median over
rounds of each group's ms per frame, their sum, and the wall time per frame (the same difference
of ``metrics.json``'s ``wall_s``). A thread is measured to its last sample: one that ends early
(the loader's, once every frame is decoded) loses what it ran after it, at most 20 ms, and so does
every thread at the run's end: over B - A = 144 frames that is 0.14 ms per frame. Linux only. The sequence is a folder under ``$TORCHSLAM_DATA``
or a path.

What it tells: whether a run's rate is bound by one thread (its ms per frame near the wall time
per frame) or by the machine's cores (the sum near cores x wall time per frame).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench import RESULTS, data_root, load_average, write_json

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _tree(pid: int) -> list[int]:
    """``pid`` and every descendant process."""
    out = [pid]
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                for child in f.read().split():
                    out += _tree(int(child))
    except OSError:
        pass
    return out


MAIN = "main (tracking)"


def _sample(pids: list[int], last: dict) -> None:
    """Record each thread's name and CPU seconds so far into ``last[(pid, tid)]``; the first pid's
    main thread (the run's own, which tracks) is named ``MAIN``."""
    for pid in pids:
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    stat = f.read()
            except OSError:
                continue
            name = MAIN if int(tid) == pids[0] else stat[stat.index("(") + 1:stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2:].split()
            last[(pid, int(tid))] = (name, (int(fields[11]) + int(fields[12])) / _TICK)


def measure(cmd: list[str], interval: float = 0.02) -> dict[str, float]:
    """Run ``cmd`` and return the CPU seconds of its threads, summed by thread name."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    last: dict = {}
    while proc.poll() is None:
        _sample(_tree(proc.pid), last)
        time.sleep(interval)
    err = proc.stderr.read()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {proc.returncode}):\n{err[-2000:]}")
    by_name: dict[str, float] = {}
    for name, seconds in last.values():
        by_name[name] = by_name.get(name, 0.0) + seconds
    return by_name


def run_once(system: str, sequence: Path, frames: int, sets: list[str], folder: Path) -> tuple[dict[str, float], float]:
    """CPU seconds by thread name and ``wall_s`` of one ``torchslam run`` over the first ``frames`` frames."""
    out = folder / f"run-{frames}"
    cmd = [sys.executable, "-m", "torchslam", "run", "--system", system, "--data", str(sequence), "--out", str(out),
           "--overwrite", "--no-tensorboard", "--no-progress", "--max-frames", str(frames)]
    for s in sets:
        cmd += ["--set", s]
    cpu = measure(cmd)
    wall = json.loads((out / "metrics.json").read_text())["wall_s"]
    return cpu, wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--system", default="nislam")
    ap.add_argument("--sequence", default="tum_fr1_xyz", help="a folder under $TORCHSLAM_DATA, or a path")
    ap.add_argument("--frames", default="60,204", help="A,B: the two runs' frame counts, A < B")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], help="passed to torchslam run (repeatable)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_cpu.json")
    args = ap.parse_args()
    if not Path("/proc/self/task").is_dir():
        ap.error("needs Linux's /proc")
    try:
        a, b = (int(x) for x in args.frames.split(","))
    except ValueError:
        ap.error(f"--frames: expected A,B, got {args.frames!r}")
    if not 1 <= a < b:
        ap.error(f"--frames: expected 1 <= A < B, got {a},{b}")
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    sequence = Path(args.sequence)
    if not sequence.is_dir():
        sequence = data_root() / args.sequence
    if not sequence.is_dir():
        ap.error(f"--sequence: no folder {args.sequence} (nor under {data_root()})")
    env_threads = os.environ.get("OMP_NUM_THREADS")
    print(f"load {load_average()}; {args.system} on {sequence.name}, frames {a} and {b}, OMP_NUM_THREADS={env_threads}", flush=True)
    per_round: list[dict[str, float]] = []
    walls: list[float] = []
    with tempfile.TemporaryDirectory(prefix="torchslam-bench-cpu-") as tmp:
        for r in range(args.rounds):
            cpu_a, wall_a = run_once(args.system, sequence, a, args.set, Path(tmp))
            cpu_b, wall_b = run_once(args.system, sequence, b, args.set, Path(tmp))
            names = set(cpu_a) | set(cpu_b)
            per_round.append({n: 1000 * (cpu_b.get(n, 0.0) - cpu_a.get(n, 0.0)) / (b - a) for n in names})
            walls.append(1000 * (wall_b - wall_a) / (b - a))
            print(f"round {r + 1}: " + ", ".join(f"{n} {v:.1f}" for n, v in sorted(per_round[-1].items(), key=lambda kv: -kv[1]))
                  + f" ms/frame; wall {walls[-1]:.1f} ms/frame", flush=True)
    names = sorted({n for d in per_round for n in d})
    median = {n: statistics.median(d.get(n, 0.0) for d in per_round) for n in names}
    total = statistics.median(sum(d.values()) for d in per_round)
    wall = statistics.median(walls)
    print("\n| thread | CPU ms per frame (median) |\n|---|---:|")
    for n in sorted(names, key=lambda n: -median[n]):
        if median[n] >= 0.05:  # helper processes of a few ms in all (ldconfig) round to nothing per frame
            print(f"| {n} | {median[n]:.1f} |")
    print(f"| **all** | **{total:.1f}** |\n\nwall time per frame {wall:.1f} ms ({1000 / wall:.1f} frames/s between the two runs)")
    from torchslam.environment import environment_info

    write_json(args.out, {"machine": environment_info(), "system": args.system, "sequence": sequence.name, "frames": [a, b],
                          "set": args.set, "rounds": per_round, "wall_ms_per_frame": walls,
                          "median_ms_per_frame": median, "total_ms_per_frame": total, "median_wall_ms_per_frame": wall})


if __name__ == "__main__":
    main()
