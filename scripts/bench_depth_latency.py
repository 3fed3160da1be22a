"""The depth stream's latency (``data.depth_time_offset``): each system at 0 and at ``auto``.

    python scripts/bench_depth_latency.py [--seeds 100,101,102,103,104] [--planted -0.015]
                                          [--jitter 0.015] [--frames 300] [--size 640x480] [--no-tum]
                                          [--systems nislam,gcslam-sparse,gcslam-dense] [--out PATH]

Each case is run as ``torchslam run`` runs it (a fresh process, one torch thread, no
TensorBoard), once with ``data.depth_time_offset=0`` (the default) and once with ``auto`` (the
latency estimated from the images when the folder opens), for NI-SLAM and both GC-SLAM
front-ends at their defaults:

- each of ``--seeds``: a synthetic sequence (``torchslam synth``'s default orbit, depth noise on)
  written as a TUM folder whose depth images are taken ``--planted`` seconds after their stamps,
  the depth stamps jittered uniformly by ``--jitter`` (the held-out split: seeds from 100);
- unless ``--no-tum``: TUM fr1/xyz from ``TORCHSLAM_DATA`` (default ``../shared/data``), the
  tuning sequence.

Reported per run: ATE (cm, evo's on the run folder's files), the latency used (ms) and the
frame rate. Results: ``scripts/results/depth_latency/``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench import RESULTS, data_root, write_json

SETTINGS = {
    "nislam": ["--system", "nislam"],
    "gcslam-sparse": ["--system", "gcslam", "--set", "frontend=sparse"],
    "gcslam-dense": ["--system", "gcslam", "--set", "frontend=dense"],
}


def _torchslam(*args: str) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-m", "torchslam", *args], check=True, env=env, stdout=subprocess.DEVNULL)


def _run(folder: Path, system: str, offset: str, out: Path) -> dict:
    _torchslam("run", *SETTINGS[system], "--data", str(folder), "--out", str(out), "--no-tensorboard", "--no-progress",
               "--set", f"data.depth_time_offset={offset}")
    m = json.loads((out / "metrics.json").read_text())
    return {"ate_cm": 100.0 * m["ate_rmse_m"], "depth_time_offset_ms": 1000.0 * m["depth_time_offset_s"],
            "fps_end_to_end": m["fps_end_to_end"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="100,101,102,103,104")
    ap.add_argument("--planted", type=float, default=-0.015, help="the synthetic depth latency, seconds")
    ap.add_argument("--jitter", type=float, default=0.015, help="the synthetic depth stamps' jitter, seconds")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="640x480", help="the synthetic images' WIDTHxHEIGHT")
    ap.add_argument("--no-tum", action="store_true", help="leave TUM fr1/xyz out")
    ap.add_argument("--systems", default=",".join(SETTINGS), help=f"any of {', '.join(SETTINGS)}, comma-separated")
    ap.add_argument("--out", type=Path, default=RESULTS / "depth_latency" / "bench_depth_latency.json")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s]
    systems = [s for s in args.systems.split(",") if s]
    unknown = [s for s in systems if s not in SETTINGS]
    if unknown or not systems:
        ap.error(f"--systems {args.systems}: expected some of {', '.join(SETTINGS)}")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size {args.size}: expected WIDTHxHEIGHT, e.g. 640x480")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = []
        for seed in seeds:
            folder = Path(tmp) / f"synthetic{seed}"
            _torchslam("synth", "--out", str(folder), "--seed", str(seed), "--frames", str(args.frames),
                       "--width", str(width), "--height", str(height),
                       "--set", f"depth_time_offset={args.planted}", "--set", f"depth_stamp_jitter={args.jitter}")
            cases.append((f"synthetic seed {seed}", "held out" if seed >= 100 else "tuning", folder))
        fr1 = data_root() / "tum_fr1_xyz"
        if not args.no_tum:
            if fr1.is_dir():
                cases.append(("tum_fr1_xyz", "tuning", fr1))
            else:
                print(f"{fr1}: absent, left out")
        for name, split, folder in cases:
            for system in systems:
                runs = {off: _run(folder, system, off, Path(tmp) / f"{folder.name}-{system}-{off}") for off in ("0", "auto")}
                rows.append({"sequence": name, "split": split, "system": system, "default": runs["0"], "auto": runs["auto"]})
                print(f"{split:9s} {name:20s} {system:14s} ATE {runs['0']['ate_cm']:.3f} -> {runs['auto']['ate_cm']:.3f} cm"
                      f"  (latency {runs['auto']['depth_time_offset_ms']:+.1f} ms)", flush=True)
    write_json(args.out, {"planted_s": args.planted, "jitter_s": args.jitter, "frames": args.frames, "size": [width, height],
                          "threads": 1, "rows": rows})


if __name__ == "__main__":
    main()
