"""Benchmark the block Cholesky's two schedules: front by front against level by level.

On FastGO's normal equations of repeated-route pose graphs
(:func:`torchslam.fastgo.synthetic.loop_route_problem`, N keyframes, linearised at the drifted
start), for both fill-reducing orders, it measures:

* **launches**: the ``torch.linalg.cholesky_ex`` and ``solve_triangular`` calls of one
  factorisation and one solve (counted with a ``TorchFunctionMode``). The ``front`` schedule
  makes one of each per supernode, the ``level`` schedule one per group (a level of the
  elimination tree, split by size class: the depth times a few), whatever the number of
  supernodes in a level;
* **time** of one factorisation plus one solve, the two schedules interleaved in one process
  (ABBA order, ``--repeat`` rounds, the median and best of each), on one torch thread unless
  ``--threads`` says otherwise, with the machine's load average printed before and after;
* the largest relative difference of the two solutions.

Writes ``scripts/results/bench_cholesky_schedule.json`` and prints a markdown table. Usage::

    python scripts/bench_cholesky_schedule.py [--sizes 600 5000] [--repeat 7] [--threads 1] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from torch.overrides import TorchFunctionMode

from _bench import RESULTS, load_average, sync
from torchslam.fastgo import FastGOConfig, assemble, linearize
from torchslam.fastgo.optimize import FastGOProblem, _prepare
from torchslam.fastgo.synthetic import loop_route_problem
from torchslam.optim import analyze, block_cholesky

SCHEDULES = ("front", "level")


class CountCalls(TorchFunctionMode):
    """Count the dense factorisation and triangular-solve calls made inside the block."""

    def __init__(self) -> None:
        super().__init__()
        self.cholesky = 0
        self.solve_triangular = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is torch.linalg.cholesky_ex:
            self.cholesky += 1
        elif func is torch.linalg.solve_triangular:
            self.solve_triangular += 1
        return func(*args, **(kwargs or {}))


def normal_equations(num_keyframes: int, device: str):
    """FastGO's ``(H, rhs, fixed)`` of a repeated-route graph at its drifted start."""
    P = loop_route_problem(num_keyframes)
    work = _prepare([FastGOProblem(P.T_init, P.pairs, P.stats)], FastGOConfig())
    H, g = assemble(linearize(work.T, work.pairs, work.stats), work.pairs, num_keyframes)
    H = type(H)(H.diag.to(device), H.off.to(device), H.rows.to(device), H.cols.to(device))
    return H, -g.to(device), work.fixed


def bench(num_keyframes: int, ordering: str, repeat: int, device: str) -> dict:
    """Launches and interleaved timings of both schedules on one graph and order."""
    H, rhs, fixed = normal_equations(num_keyframes, device)
    sym = analyze(num_keyframes, H.rows, H.cols, fixed, 6, FastGOConfig().leaf_size, ordering)
    row = {"keyframes": num_keyframes, "ordering": ordering, "fronts": sym.num_fronts, "depth": sym.depth,
           "groups": sym.num_groups, "factor_nnz": sym.factor_nnz}
    x = {}
    with torch.no_grad():
        for s in SCHEDULES:
            fac = block_cholesky(H, sym, s)  # warm-up: index tensors on the device, allocator
            x[s] = fac.solve(rhs)
            with CountCalls() as calls:
                block_cholesky(H, sym, s).solve(rhs)
            row[f"{s}_launches"] = calls.cholesky + calls.solve_triangular
            row[f"{s}_cholesky_calls"] = calls.cholesky
        seconds = {s: [] for s in SCHEDULES}
        for r in range(repeat):
            for s in SCHEDULES if r % 2 == 0 else SCHEDULES[::-1]:
                sync(device)
                t0 = time.perf_counter()
                block_cholesky(H, sym, s).solve(rhs)
                sync(device)
                seconds[s].append(time.perf_counter() - t0)
    for s in SCHEDULES:
        row[f"{s}_ms"] = statistics.median(seconds[s]) * 1e3
        row[f"{s}_best_ms"] = min(seconds[s]) * 1e3
    row["level_over_front"] = row["level_ms"] / row["front_ms"]
    row["max_rel_diff"] = float((x["level"] - x["front"]).norm() / x["front"].norm())
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[600, 5000])
    ap.add_argument("--orderings", nargs="+", default=["band", "nested"])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(RESULTS / "bench_cholesky_schedule.json"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load_before = load_average()
    print(f"threads {torch.get_num_threads()}, device {args.device}, load average before {load_before}", flush=True)
    rows = []
    for n in args.sizes:
        for ordering in args.orderings:
            rows.append(bench(n, ordering, args.repeat, args.device))
            r = rows[-1]
            print(f"  N={n} {ordering}: fronts {r['fronts']}, depth {r['depth']}, groups {r['groups']}, launches {r['front_launches']} -> "
                  f"{r['level_launches']}, {r['front_ms']:.1f} -> {r['level_ms']:.1f} ms", flush=True)
    load_after = load_average()
    print(f"load average after {load_after}\n")
    print("| N | order | fronts | depth | level groups | launches front / level | front ms (best) | level ms (best) | level / front | max rel diff |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['keyframes']} | {r['ordering']} | {r['fronts']} | {r['depth']} | {r['groups']} | {r['front_launches']} / {r['level_launches']} "
              f"| {r['front_ms']:.1f} ({r['front_best_ms']:.1f}) | {r['level_ms']:.1f} ({r['level_best_ms']:.1f}) "
              f"| {r['level_over_front']:.2f} | {r['max_rel_diff']:.1e} |")
    out = {"threads": torch.get_num_threads(), "device": args.device, "repeat": args.repeat,
           "load_before": load_before, "load_after": load_after, "rows": rows}
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
