"""End-to-end frames/s of this checkout against another one, in alternating subprocesses.

    python scripts/bench_checkouts.py --other ../main-old [--systems nislam,gcslam-sparse,gcslam-dense]
                                      [--sequences tum_fr1_xyz,7scenes_redkitchen] [--rounds 3] [--busy N]

Each round runs every (system, sequence) once with each checkout, one after the other, each in
a fresh process whose ``PYTHONPATH`` puts that checkout's ``torchslam`` first: the whole of
``run_sequence`` at the defaults (the loader decoding ahead, GC-SLAM optimising in the
background), as ``torchslam run`` does it, so what one checkout does on other threads is
measured too. Alternating within a round lets drifts of the machine's speed hit both alike;
``--busy N`` runs N competing busy-loop processes throughout (a machine shared with other work).
Reports the median frames/s end to end of each checkout, their ratio, and both ATEs (which
must agree where the change is meant to keep results). One torch thread. Results:
``scripts/results/bench_checkouts.json`` (``--out``).

``--worker SYSTEM SEQUENCE`` is the subprocess's own entry point (prints one JSON line).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from _bench import RESULTS, ate_cm, data_root, load_average, start_load, stop_load, system_by_name, write_json

HERE = Path(__file__).resolve()


def _worker(system: str, sequence: str) -> None:
    import torch

    torch.set_num_threads(1)
    import torchslam
    from torchslam.data.tum import TUMSequence
    from torchslam.systems import run_sequence

    seq = TUMSequence(data_root() / sequence, prefetch=2)
    res = run_sequence(system_by_name(system), seq)
    err = ate_cm(res.output, seq)
    print(json.dumps({"fps": res.fps_end_to_end, "ate_cm": err, "torchslam": str(Path(torchslam.__file__).parent)}))


def _run(checkout: Path, system: str, sequence: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(HERE), "--worker", system, sequence], env=env, capture_output=True, text=True,
                          cwd=checkout, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{checkout}: {system} on {sequence} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--other", type=Path, help="the checkout to compare against (its repository root)")
    ap.add_argument("--systems", default="nislam,gcslam-sparse,gcslam-dense")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_checkouts.json")
    ap.add_argument("--busy", type=int, default=0, help="competing busy-loop processes (one core each) during the runs")
    ap.add_argument("--worker", nargs=2, metavar=("SYSTEM", "SEQUENCE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(*args.worker)
        return
    if args.other is None:
        ap.error("--other is required")
    if args.busy < 0:
        ap.error("--busy must be 0 or more")
    trees = {"other": args.other.resolve(), "this": HERE.parents[1]}
    print(f"load {load_average()}; other = {trees['other']}, this = {trees['this']}; busy processes {args.busy}", flush=True)
    load = start_load(args.busy)
    try:
        rows = _compare(args, trees)
    finally:
        stop_load(load)
    from torchslam.environment import environment_info

    write_json(args.out, {"machine": environment_info(), "other": str(trees["other"]), "rounds": args.rounds, "threads": 1,
                          "busy": args.busy, "rows": rows})


def _compare(args, trees: dict[str, Path]) -> list[dict]:
    """Every (system, sequence) of ``args`` with both checkouts, ``args.rounds`` alternating rounds."""
    rows = []
    for system in args.systems.split(","):
        for sequence in args.sequences.split(","):
            fps: dict[str, list[float]] = {k: [] for k in trees}
            ate: dict[str, float | None] = {}
            for _ in range(args.rounds):
                for label, path in trees.items():
                    r = _run(path, system, sequence)
                    if Path(r["torchslam"]).resolve() != path / "torchslam":
                        raise SystemExit(f"{label}: imported torchslam from {r['torchslam']}, not from {path}")
                    fps[label].append(r["fps"])
                    ate[label] = r["ate_cm"]
            med = {k: statistics.median(v) for k, v in fps.items()}
            row = {"system": system, "sequence": sequence, "fps": fps, "median": med, "ratio": med["this"] / med["other"],
                   "ate_cm": ate, "load": load_average()}
            rows.append(row)
            print(f"{system:14s} {sequence:20s} other {med['other']:5.1f}  this {med['this']:5.1f} frames/s ({row['ratio']:.2f} x)  "
                  f"ATE {ate['other']:.3f} -> {ate['this']:.3f} cm", flush=True)
    return rows


if __name__ == "__main__":
    main()
