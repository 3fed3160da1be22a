"""GC-SLAM's rolling-shutter model (``readout_time``): a front-end without and with it.

    python scripts/bench_rolling_shutter.py [--seeds 100,101,102,103,104] [--planted 0.03]
                                            [--readout 0.03] [--frames 300] [--size 640x480] [--trajectory orbit]
                                            [--real tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs]
                                            [--stride 1] [--jobs 2] [--frontend dense|sparse] [--out PATH]

Each case is run as ``torchslam run`` runs it (a fresh process, one torch thread, no
TensorBoard), GC-SLAM's ``--frontend`` (dense unless set) at its defaults, once with ``readout_time=0`` (a
global shutter) and once with ``readout_time=--readout`` (both set explicitly: the default,
``auto``, takes the sequence's own readout):

- each of ``--seeds``: a synthetic sequence (``torchslam synth``, depth noise on) whose rows are
  read out over ``--planted`` seconds, top row first (the held-out split: seeds from 100), and
  the same sequence rendered with a global shutter, run at ``readout_time=0`` (the reference:
  what the model could give back at most);
- each of ``--real`` present under ``TORCHSLAM_DATA`` (default ``../shared/data``): TUM fr1/xyz
  and 7-Scenes come from a Kinect v1, whose two cameras have rolling shutters; the HoloLens
  depth camera is not one of those, so its row shows what a wrong setting costs.

``--stride N`` runs every N-th frame of each sequence (``data.stride``: faster motion between
the frames tracked, and a motion estimate over a longer step).

Reported per run: ATE (cm, evo's on the run folder's files), keyframes, frames and keyframes the
model moved, frame rate. ``--jobs`` runs that many at once (ATE only: the frame rates are then
not an idle machine's). Results: ``scripts/results/rolling_shutter/``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from _bench import RESULTS, data_root, write_json

REAL = {"tum_fr1_xyz": "tuning", "7scenes_redkitchen": "tuning", "hololens_dvmvs": "held out"}


def _torchslam(*args: str) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-m", "torchslam", *args], check=True, env=env, stdout=subprocess.DEVNULL)


def _run(folder: Path, readout: float, out: Path, stride: int = 1, frontend: str = "dense") -> dict:
    _torchslam("run", "--system", "gcslam", "--set", f"frontend={frontend}", "--set", f"readout_time={readout}", "--data", str(folder),
               "--set", f"data.stride={stride}", "--out", str(out), "--no-tensorboard", "--no-progress")
    m = json.loads((out / "metrics.json").read_text())
    return {"readout_time_s": readout, "ate_cm": 100.0 * m["ate_rmse_m"], "keyframes": m["keyframes"],
            "moved": {k: m["rolling_shutter"][k] for k in ("frames", "keyframes")},
            "fps_end_to_end": m["fps_end_to_end"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="100,101,102,103,104")
    ap.add_argument("--planted", type=float, default=0.03, help="the synthetic sensor's readout, seconds")
    ap.add_argument("--readout", type=float, default=0.03, help="readout_time of the runs with the model, seconds")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="640x480", help="the synthetic images' WIDTHxHEIGHT")
    ap.add_argument("--trajectory", default="orbit", help="the synthetic trajectory (torchslam synth's)")
    ap.add_argument("--real", default=",".join(REAL), help="real sequences under TORCHSLAM_DATA, comma-separated ('' for none)")
    ap.add_argument("--stride", type=int, default=1, help="run every N-th frame (data.stride)")
    ap.add_argument("--jobs", type=int, default=2, help="runs at once")
    ap.add_argument("--frontend", choices=("dense", "sparse"), default="dense", help="GC-SLAM's front-end")
    ap.add_argument("--out", type=Path, default=RESULTS / "rolling_shutter" / "bench_rolling_shutter.json")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s]
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: expected at least 1")
    if args.stride < 1:
        ap.error(f"--stride {args.stride}: expected at least 1")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size {args.size}: expected WIDTHxHEIGHT, e.g. 640x480")
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(args.jobs) as pool:
        tmp = Path(tmp)

        def synth(seed: int, planted: float) -> Path:
            folder = tmp / f"synthetic{seed}-readout{planted}"
            _torchslam("synth", "--out", str(folder), "--seed", str(seed), "--frames", str(args.frames),
                       "--width", str(width), "--height", str(height), "--set", f"trajectory={args.trajectory}", "--set", f"readout_time={planted}")
            return folder

        folders = {(seed, p): pool.submit(synth, seed, p) for seed in seeds for p in (args.planted, 0.0)}
        jobs = []  # (sequence, split, kind, future)
        for seed in seeds:
            split = "held out" if seed >= 100 else "tuning"
            rs, gs = folders[(seed, args.planted)].result(), folders[(seed, 0.0)].result()
            name = f"synthetic {args.trajectory} seed {seed}"
            jobs.append((name, split, "without", pool.submit(_run, rs, 0.0, tmp / f"{rs.name}-0", args.stride, args.frontend)))
            jobs.append((name, split, "with", pool.submit(_run, rs, args.readout, tmp / f"{rs.name}-r", args.stride, args.frontend)))
            jobs.append((name, split, "global_shutter", pool.submit(_run, gs, 0.0, tmp / f"{gs.name}-0", args.stride, args.frontend)))
        for name in [n for n in args.real.split(",") if n]:
            folder = data_root() / name
            if not folder.is_dir():
                print(f"{folder}: absent, left out")
                continue
            split = REAL.get(name, "held out")
            jobs.append((name, split, "without", pool.submit(_run, folder, 0.0, tmp / f"{name}-0", args.stride, args.frontend)))
            jobs.append((name, split, "with", pool.submit(_run, folder, args.readout, tmp / f"{name}-r", args.stride, args.frontend)))
        rows: dict[str, dict] = {}
        for name, split, kind, fut in jobs:
            rows.setdefault(name, {"sequence": name, "split": split})[kind] = fut.result()
        for row in rows.values():
            ref = f", global shutter {row['global_shutter']['ate_cm']:.3f}" if "global_shutter" in row else ""
            print(f"{row['split']:9s} {row['sequence']:28s} ATE {row['without']['ate_cm']:.3f} -> {row['with']['ate_cm']:.3f} cm{ref}")
    write_json(args.out, {"planted_s": args.planted, "readout_s": args.readout, "frames": args.frames, "size": [width, height],
                          "trajectory": args.trajectory, "stride": args.stride, "frontend": args.frontend, "threads": 1, "jobs": args.jobs, "rows": list(rows.values())})


if __name__ == "__main__":
    main()
