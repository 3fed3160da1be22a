"""How NI-SLAM's IMU attitude starts on a TUM folder with ``imu.txt``, with and without its ground truth.

    python scripts/bench_imu_start.py [--seeds 0,1,2,3,100,101,102,103] [--walks 7:0 107:0 ...]
                                      [--frames 300] [--out PATH]

A folder's attitude filter starts at the ground truth's rotation where ``groundtruth.txt`` has
one in a z-up world, else levelled by gravity with zero yaw (``TUMSequence``, ``imu.start_up``).
Each case is a synthetic sequence written as a TUM folder (``torchslam synth``'s writer, with
``imu.txt``): the ``handheld`` trajectory for each of ``--seeds``, and for each ``--walks``
``SEED:EXPOSURE`` the fast walk of ``bench_fast_motion.py`` (the ``loop`` trajectory at a 3.4 s
period, 313 frames, about 8 cm and 3.5 degrees between frames, its colour averaged over
``EXPOSURE`` seconds). Seeds below 100 are the tuning split, from 100 the held-out one.

Each folder is run twice at the default settings (one torch thread), once as written and once
through a copy without ``groundtruth.txt`` (links to the same files), and both trajectories are
scored against the ground truth (evo's ATE, SE(3)). Reported per case: whether the ground truth
started the filter, the start's tilt error either way (degrees, against the true first
rotation), ATE (cm) and loops accepted of verified. Results: ``scripts/results/imu_start/``.
"""

from __future__ import annotations

import argparse
import logging
import math
import tempfile
from pathlib import Path

import torch

from _bench import RESULTS, ate_cm, system_by_name, write_json
from bench_fast_motion import FAST_WALK, _blur_cases, _seed_split
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
from torchslam.data.tum import TUMSequence
from torchslam.imu import attitude_errors
from torchslam.systems import run_sequence

FOLDER_FILES = ("rgb", "depth", "rgb.txt", "depth.txt", "imu.txt", "calibration.txt")


def _without_groundtruth(folder: Path, into: Path) -> Path:
    """A folder of links to ``folder``'s files, ``groundtruth.txt`` left out."""
    into.mkdir(parents=True)
    for name in FOLDER_FILES:
        if (folder / name).exists():
            (into / name).symlink_to(folder / name)
    return into


def _run(folder: Path, reference: TUMSequence) -> dict:
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logging.getLogger("torchslam.data.tum").addHandler(handler)
    try:
        seq = TUMSequence(folder)
    finally:
        logging.getLogger("torchslam.data.tum").removeHandler(handler)
    R0 = seq.attitude.at(seq.timestamps[:1])[0]
    tilt, _ = attitude_errors(R0, reference.groundtruth.T_wc[:1, :3, :3])
    out = run_sequence(system_by_name("nislam"), seq)
    loops = out.output.metrics.get("loops", {})
    return {
        "groundtruth_start": (folder / "groundtruth.txt").exists() and not any("not z-up" in r.getMessage() for r in records),
        "start_tilt_deg": round(math.degrees(float(tilt[0])), 3),
        "ate_cm": round(ate_cm(out.output, reference), 3),
        "loops_accepted": loops.get("accepted"),
        "loops_verified": loops.get("verified"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,100,101,102,103", help="handheld seeds ('' for none)")
    ap.add_argument("--walks", nargs="*", default=["7:0", "107:0", "7:0.02", "107:0.02"], help="fast walks SEED:EXPOSURE")
    ap.add_argument("--frames", type=int, default=300, help="frames of each handheld sequence")
    ap.add_argument("--out", type=Path, default=RESULTS / "imu_start" / "bench_imu_start.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cases = [(f"handheld-{s}", int(s), SyntheticConfig(seed=int(s), frames=args.frames, trajectory="handheld"))
             for s in args.seeds.split(",") if s.strip()]
    for seed, exposure in _blur_cases(args.walks, "--walks"):
        cases.append((f"fast-walk-{seed}-exposure{exposure:g}", seed, SyntheticConfig(seed=seed, exposure=exposure, **FAST_WALK)))
    rows = []
    print(f"{'case':28s} {'split':9s} {'folder start':>12s} {'tilt':>6s} {'ATE':>7s} {'loops':>6s} | {'levelled':>8s} {'tilt':>6s} {'ATE':>7s} {'loops':>6s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, seed, cfg in cases:
            folder = Path(tmp) / name
            write_tum_folder(generate_sequence(cfg), folder)
            reference = TUMSequence(folder)
            with_gt = _run(folder, reference)
            levelled = _run(_without_groundtruth(folder, Path(tmp) / f"{name}-no-gt"), reference)
            row = {"case": name, "split": _seed_split(seed), "as_written": with_gt, "without_groundtruth": levelled}
            rows.append(row)
            a, b = with_gt, levelled
            print(
                f"{name:28s} {row['split']:9s} {'truth' if a['groundtruth_start'] else 'levelled':>12s} {a['start_tilt_deg']:6.2f} "
                f"{a['ate_cm']:7.3f} {a['loops_accepted']}/{a['loops_verified']:<4} | {'levelled':>8s} {b['start_tilt_deg']:6.2f} "
                f"{b['ate_cm']:7.3f} {b['loops_accepted']}/{b['loops_verified']:<4}",
                flush=True,
            )
    write_json(args.out, {"threads": 1, "rows": rows})


if __name__ == "__main__":
    main()
