"""The C heap kept between frames (``TORCHSLAM_MALLOC=retain``, the default) against the C library's defaults (``system``).

    python scripts/bench_malloc.py [--rounds 2] [--sequences tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs]
                                   [--systems nislam,gcslam-sparse,gcslam-dense] [--busy-procs 1]

The setting belongs to the process, so every run is a fresh process (this script started again
with ``--child``), the two settings alternating within each round so that drifts of the
machine's speed hit both alike. Each child runs one system on one sequence through
``run_sequence`` (the loader decoding ahead on its own thread, as ``torchslam run`` does) and
reports frames/s end to end, the minor page faults and the system's stage milliseconds per frame,
the peak resident memory and a digest of the trajectory (the two settings must give the same
bits). Two conditions: ``idle`` and ``busy`` (``--busy-procs`` pure-Python busy loops, started and
stopped by the script). One torch thread unless ``--threads``. Results:
``scripts/results/bench_malloc.json``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _bench import (
    ALLOCATOR, RESULTS, add_matrix_arguments, ate_cm, data_root, load_average, run_conditions, system_by_name, write_json,
)

SPLIT = {"tum_fr1_xyz": "tuning", "7scenes_redkitchen": "tuning", "hololens_dvmvs": "held out"}
MODES = ("system", "retain")


def _child(system_name: str, sequence: str, threads: int) -> dict:
    import torch

    from torchslam.data.tum import TUMSequence
    from torchslam.systems import run_sequence

    torch.set_num_threads(threads)
    seq = TUMSequence(data_root() / sequence, prefetch=2)
    system = system_by_name(system_name)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    res = run_sequence(system, seq)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    out = res.output
    n = len(seq)
    return {
        "malloc": ALLOCATOR.mode,
        "malloc_applied": ALLOCATOR.applied,
        "fps": res.fps_end_to_end,
        "faults_per_frame": faults / n,
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "stage_ms": {k: v / n for k, v in system.stage_ms.items()},
        "ate_cm": ate_cm(out, seq),
        "trajectory_sha1": hashlib.sha1(out.T_wc.double().contiguous().numpy().tobytes()).hexdigest(),
    }


def _spawn(system_name: str, sequence: str, mode: str, threads: int) -> dict:
    env = {**os.environ, "TORCHSLAM_MALLOC": mode, "OMP_NUM_THREADS": str(threads)}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", f"{system_name}:{sequence}", "--threads", str(threads)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{system_name} on {sequence} with TORCHSLAM_MALLOC={mode} failed:\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    add_matrix_arguments(ap, RESULTS / "bench_malloc.json")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        system_name, sequence = args.child.split(":", 1)
        print(json.dumps(_child(system_name, sequence, args.threads)))
        return
    from torchslam.environment import environment_info

    rows = []
    print(f"threads {args.threads}, load {load_average()}, {time.strftime('%H:%M:%S')}", flush=True)
    for condition in run_conditions(args.busy_procs):
        for system_name in args.systems.split(","):
            for sequence in args.sequences.split(","):
                runs: dict[str, list[dict]] = {m: [] for m in MODES}
                for r in range(args.rounds):
                    # Alternate which setting goes first, so neither always runs on a cooler machine.
                    for mode in MODES if r % 2 == 0 else MODES[::-1]:
                        runs[mode].append(_spawn(system_name, sequence, mode, args.threads))
                row = {"condition": condition, "system": system_name, "sequence": sequence,
                       "split": SPLIT.get(sequence, "?"), "runs": runs, "load": load_average()}
                for mode in MODES:
                    row[mode] = {
                        "fps_median": statistics.median(x["fps"] for x in runs[mode]),
                        "faults_per_frame_median": statistics.median(x["faults_per_frame"] for x in runs[mode]),
                        "max_rss_mb_max": max(x["max_rss_mb"] for x in runs[mode]),
                        "ate_cm": runs[mode][0]["ate_cm"],
                    }
                row["ratio"] = row["retain"]["fps_median"] / row["system"]["fps_median"]
                digests = {x["trajectory_sha1"] for m in MODES for x in runs[m]}
                row["identical"] = len(digests) == 1
                rows.append(row)
                s, k = row["system"], row["retain"]
                print(
                    f"{condition:4s} {system_name:13s} {sequence:19s} frames/s {s['fps_median']:5.1f} -> {k['fps_median']:5.1f}"
                    f" ({row['ratio']:.2f}x)  faults/frame {s['faults_per_frame_median']:6.0f} -> {k['faults_per_frame_median']:5.0f}"
                    f"  peak RSS {s['max_rss_mb_max']:5.0f} -> {k['max_rss_mb_max']:5.0f} MB  identical {row['identical']}",
                    flush=True,
                )
    write_json(Path(args.out), {"environment": environment_info(), "threads": args.threads, "rounds": args.rounds,
                                "busy_procs": args.busy_procs, "rows": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
