"""Seconds from a fresh interpreter to a run's first tracked frame: this checkout against another.

    python scripts/bench_startup.py --other ../main-old [--systems nislam,gcslam] \
        [--sequences tum_fr1_xyz,7scenes_redkitchen] [--rounds 5]

What a user waits for before tracking starts and what ``fps_end_to_end`` leaves out: importing
torchslam, reading the sequence (its ground truth included) and the system's ``start``. Each
round runs ``torchslam run ... --max-frames 5`` once with each checkout, alternating which goes
first, each in a fresh process whose ``PYTHONPATH`` puts that checkout first, and reads three
instants from inside it: the system's ``start`` called and returned, and the first frame's
``track`` returned. Reports their medians per checkout. One torch thread. Results:
``scripts/results/startup_costs/bench_startup.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench import RESULTS, data_root, load_average, write_json

# Runs inside the measured process: times the three instants against the interpreter's start.
_PROBE = r"""
import json, sys, time
t0 = time.perf_counter()
import importlib
marks = {}
module, name = {"nislam": ("torchslam.systems.nislam", "NISlam"), "gcslam": ("torchslam.systems.gcslam", "GCSlam")}[sys.argv[1]]
cls = getattr(importlib.import_module(module), name)
start, track = cls.start, cls.track
def timed_start(self, *a, **k):
    marks.setdefault("start_called_s", time.perf_counter() - t0)
    out = start(self, *a, **k)
    marks.setdefault("start_returned_s", time.perf_counter() - t0)
    return out
def timed_track(self, *a, **k):
    out = track(self, *a, **k)
    marks.setdefault("first_frame_s", time.perf_counter() - t0)
    return out
cls.start, cls.track = timed_start, timed_track
from torchslam.cli import main
try:
    main(["run", "--system", sys.argv[1], "--data", sys.argv[2], "--out", sys.argv[3], "--overwrite",
          "--max-frames", "5", "--no-progress", "--no-tensorboard"])
except SystemExit as exc:
    if exc.code:
        raise
marks["torchslam"] = sys.modules["torchslam"].__file__
print(json.dumps(marks))
"""


def _measure(tree: Path, system: str, data: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", TORCHSLAM_THREADS="1")
    with tempfile.TemporaryDirectory() as out:
        # cwd elsewhere: ``python -c`` puts the working directory first on sys.path, before PYTHONPATH.
        proc = subprocess.run([sys.executable, "-c", _PROBE, system, str(data), str(Path(out) / "run")],
                              env=env, cwd=out, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", type=Path, required=True, help="the checkout to compare against (its repository root)")
    ap.add_argument("--systems", default="nislam,gcslam")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "startup_costs" / "bench_startup.json")
    args = ap.parse_args()
    trees = {"other": args.other.resolve(), "this": Path(__file__).resolve().parents[1]}
    print(f"load {load_average()}; other = {trees['other']}, this = {trees['this']}")
    rows = []
    for system in args.systems.split(","):
        for name in args.sequences.split(","):
            marks: dict[str, list[dict]] = {"other": [], "this": []}
            for r in range(args.rounds):
                for label in (("other", "this") if r % 2 == 0 else ("this", "other")):
                    marks[label].append(_measure(trees[label], system, data_root() / name))
            row = {"system": system, "sequence": name, "rounds": args.rounds}
            for label, runs in marks.items():
                if any(Path(m["torchslam"]).parents[1] != trees[label] for m in runs):
                    raise SystemExit(f"the {label} runs imported {runs[0]['torchslam']}, not {trees[label]}'s torchslam")
                row[label] = {k: statistics.median(m[k] for m in runs) for k in runs[0] if k != "torchslam"}
            rows.append(row)
            o, t = row["other"], row["this"]
            print(f"{system:7s} {name:20s} start called {o['start_called_s']:.2f} -> {t['start_called_s']:.2f} s, "
                  f"start took {o['start_returned_s'] - o['start_called_s']:.2f} -> {t['start_returned_s'] - t['start_called_s']:.2f} s, "
                  f"first frame done {o['first_frame_s']:.2f} -> {t['first_frame_s']:.2f} s")
    write_json(args.out, {"load_average_end": load_average(), "threads": 1, "rows": rows,
                          "note": "medians over rounds; seconds from the interpreter's start"})


if __name__ == "__main__":
    main()
