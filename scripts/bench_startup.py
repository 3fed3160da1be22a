"""What a run costs outside its frames, from a fresh interpreter: this checkout against another.

    python scripts/bench_startup.py --other ../main-old [--systems nislam,gcslam] \
        [--sequences tum_fr1_xyz,7scenes_redkitchen] [--rounds 5] [--frames 5] [--tensorboard]

What a user waits for besides tracking, part of which ``fps_end_to_end`` leaves out: importing
torchslam, reading the sequence (its ground truth included), the system's ``start``, and what
follows the last frame. Each round runs ``torchslam run ... --max-frames 5`` (``--frames``; 0:
every frame) once with each checkout, alternating which goes first, each in a fresh process
whose ``PYTHONPATH`` puts that checkout first, and reads from inside it the instants at which
the system's ``start`` was called and returned, the first frame's ``track`` returned and the
process ended, and the run's ``fps_end_to_end``. Runs write no TensorBoard events unless
``--tensorboard`` (``torchslam run``'s default). Reports the medians per checkout. One torch
thread. Results: ``scripts/results/startup_costs/bench_startup.json`` (``--out``).
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
          "--no-progress"] + sys.argv[4:])
except SystemExit as exc:
    if exc.code:
        raise
marks["end_s"] = time.perf_counter() - t0
marks["fps_end_to_end"] = json.load(open(sys.argv[3] + "/metrics.json"))["fps_end_to_end"]
marks["torchslam"] = sys.modules["torchslam"].__file__
print(json.dumps(marks))
"""


def _measure(tree: Path, system: str, data: Path, tensorboard: bool = False, frames: int = 5) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", TORCHSLAM_THREADS="1")
    with tempfile.TemporaryDirectory() as out:
        extra = ([] if tensorboard else ["--no-tensorboard"]) + (["--max-frames", str(frames)] if frames > 0 else [])
        # cwd elsewhere: ``python -c`` puts the working directory first on sys.path, before PYTHONPATH.
        proc = subprocess.run([sys.executable, "-c", _PROBE, system, str(data), str(Path(out) / "run"), *extra],
                              env=env, cwd=out, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", type=Path, required=True, help="the checkout to compare against (its repository root)")
    ap.add_argument("--systems", default="nislam,gcslam")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--tensorboard", action="store_true", help="runs write TensorBoard events (as torchslam run does by default)")
    ap.add_argument("--frames", type=int, default=5, help="frames per run (0: all of them)")
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
                    m = _measure(trees[label], system, data_root() / name, args.tensorboard, args.frames)
                    if Path(m.pop("torchslam")).parents[1] != trees[label]:
                        raise SystemExit(f"the {label} run imported another torchslam, not {trees[label]}'s")
                    marks[label].append(m)
            row = {"system": system, "sequence": name, "rounds": args.rounds, "tensorboard": args.tensorboard,
                   "frames": args.frames}
            for label, runs in marks.items():
                row[label] = {k: statistics.median(m[k] for m in runs) for k in runs[0]}
            rows.append(row)
            o, t = row["other"], row["this"]
            print(f"{system:7s} {name:20s} start called {o['start_called_s']:.2f} -> {t['start_called_s']:.2f} s, "
                  f"start took {o['start_returned_s'] - o['start_called_s']:.2f} -> {t['start_returned_s'] - t['start_called_s']:.2f} s, "
                  f"first frame done {o['first_frame_s']:.2f} -> {t['first_frame_s']:.2f} s, "
                  f"process {o['end_s']:.2f} -> {t['end_s']:.2f} s, {o['fps_end_to_end']:.1f} -> {t['fps_end_to_end']:.1f} frames/s")
    write_json(args.out, {"load_average_end": load_average(), "threads": 1, "rows": rows,
                          "note": "medians over rounds; seconds from the interpreter's start"})


if __name__ == "__main__":
    main()
