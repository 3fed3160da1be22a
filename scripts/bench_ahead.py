"""Frames prepared ahead (``prepare_ahead``) against inline preparation, end to end, idle and busy.

    python scripts/bench_ahead.py [--rounds 2] [--sequences tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs]
                                  [--systems nislam,gcslam-sparse,gcslam-dense] [--busy-procs 1]

Each system runs every sequence through ``run_sequence`` (the loader decoding two frames ahead on
its own thread, as ``torchslam run`` does), with ``prepare_ahead`` off and on, alternating within
each round so that drifts of the machine's speed hit both alike; GC-SLAM optimises in its
background thread (the default). Two conditions: ``idle`` and ``busy`` (``--busy-procs``
pure-Python busy loops, started and stopped by the script). Reports the median frames/s end to
end of each setting, their ratio, and whether the trajectories are identical (they must be).
One torch thread unless ``--threads``. Results: ``scripts/results/bench_ahead.json``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from _bench import RESULTS, add_matrix_arguments, ate_cm, data_root, load_average, run_conditions, system_by_name, write_json
from torchslam.data.tum import TUMSequence
from torchslam.environment import environment_info
from torchslam.systems import run_sequence

SPLIT = {"tum_fr1_xyz": "tuning", "7scenes_redkitchen": "tuning", "hololens_dvmvs": "held out"}


def _run(system_name: str, sequence: str, ahead: bool) -> dict:
    seq = TUMSequence(data_root() / sequence, prefetch=2)
    res = run_sequence(system_by_name(system_name, prepare_ahead=ahead), seq)
    out = res.output
    return {"fps": res.fps_end_to_end, "fps_compute": res.fps_compute, "ate_cm": ate_cm(out, seq), "T_wc": out.T_wc}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    add_matrix_arguments(ap, RESULTS / "bench_ahead.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    print(f"threads {args.threads}, load {load_average()}, {time.strftime('%H:%M:%S')}", flush=True)
    for condition in run_conditions(args.busy_procs):
        for system_name in args.systems.split(","):
            for sequence in args.sequences.split(","):
                runs = {False: [], True: []}
                for _ in range(args.rounds):
                    for ahead in (False, True):
                        runs[ahead].append(_run(system_name, sequence, ahead))
                same = all(torch.equal(r["T_wc"], runs[False][0]["T_wc"]) for r in runs[False] + runs[True])
                off = statistics.median(r["fps"] for r in runs[False])
                on = statistics.median(r["fps"] for r in runs[True])
                row = {
                    "condition": condition, "system": system_name, "sequence": sequence, "split": SPLIT.get(sequence, ""),
                    "fps_inline": [r["fps"] for r in runs[False]], "fps_ahead": [r["fps"] for r in runs[True]],
                    "median_inline": off, "median_ahead": on, "ratio": on / off if off > 0 else None,
                    "ate_cm": runs[True][0]["ate_cm"], "identical": same, "load": load_average(),
                }
                rows.append(row)
                print(f"{condition:5s} {system_name:14s} {sequence:20s} inline {off:5.1f}  ahead {on:5.1f} frames/s "
                      f"({row['ratio']:.2f}x)  ATE {row['ate_cm']:.2f} cm  identical {same}", flush=True)
    write_json(Path(args.out), {
        "machine": environment_info(), "threads": args.threads, "rounds": args.rounds, "busy_procs": args.busy_procs,
        "busy_load": f"{args.busy_procs} pure-Python busy loop process(es), started and stopped by the script", "rows": rows,
    })
    print("\n| condition | system | sequence | split | frames/s inline | frames/s ahead | ratio | identical |")
    print("|---|---|---|---|---:|---:|---:|---|")
    for r in rows:
        print(f"| {r['condition']} | {r['system']} | {r['sequence']} | {r['split']} | {r['median_inline']:.1f} | {r['median_ahead']:.1f} | "
              f"{r['ratio']:.2f} × | {'yes' if r['identical'] else 'no'} |")


if __name__ == "__main__":
    main()
