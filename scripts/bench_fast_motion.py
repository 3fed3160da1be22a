"""Fast motion by frame skipping: every system on every n-th frame of the real sequences.

    python scripts/bench_fast_motion.py [--systems nislam,gcslam-sparse,gcslam-dense]
                                        [--strides hololens_dvmvs=2,3 tum_fr1_xyz=4,6 7scenes_redkitchen=4,8]

Keeping every n-th frame (``TUMSequence(stride=n)``) multiplies the motion between consecutive
frames by n while the images stay real: HoloLens at stride 2 moves about 17 cm and 7 degrees per
frame, fr1/xyz at stride 6 about as much as 5 Hz capture. It is the stress test of issue 17's
"falls apart on fast motion" on the data that ships (the fast 313-frame HoloLens walk does not).
Reports per (sequence, stride, system): frames, keyframes, ATE (evo's, SE(3)), GC-SLAM's
tracking failures and lost frames, NI-SLAM's frames on the constant-velocity prior, frames/s.
Default settings, one torch thread. Results: ``scripts/results/bench_fast_motion.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from _bench import RESULTS, SYSTEMS, ate_cm, data_root, load_average, system_by_name, write_json
from torchslam.data.tum import TUMSequence
from torchslam.systems import run_sequence

DEFAULT_STRIDES = ("hololens_dvmvs=1,2,3", "tum_fr1_xyz=4,6", "7scenes_redkitchen=4,8")


def _strides(items: list[str]) -> list[tuple[str, int]]:
    cases = []
    for item in items:
        name, sep, values = item.partition("=")
        if not sep:
            raise SystemExit(f"--strides: expected SEQUENCE=N[,N...], got {item!r}")
        try:
            cases += [(name, int(v)) for v in values.split(",")]
        except ValueError:
            raise SystemExit(f"--strides: {item!r}: strides must be integers") from None
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--strides", nargs="+", default=list(DEFAULT_STRIDES), metavar="SEQUENCE=N[,N...]")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_fast_motion.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = data_root()
    systems = args.systems.split(",")
    unknown = sorted(set(systems) - set(SYSTEMS))
    if unknown:  # before any run
        raise SystemExit(f"--systems: unknown {', '.join(unknown)} (known: {', '.join(SYSTEMS)})")
    rows = []
    for seq_name, stride in _strides(args.strides):
        if not (root / seq_name / "rgb.txt").is_file():
            print(f"  {seq_name}: not under {root}, skipped")
            continue
        for name in systems:
            seq = TUMSequence(root / seq_name, stride=stride, prefetch=2)
            t0 = time.perf_counter()
            res = run_sequence(system_by_name(name), seq)
            wall = time.perf_counter() - t0
            out = res.output
            err = ate_cm(out, seq)
            track = out.metrics.get("tracking", {})
            row = {
                "sequence": seq_name, "stride": stride, "system": name, "frames": res.frames_processed,
                "keyframes": len(out.keyframe_indices), "ate_rmse_cm": err,
                "tracking_failures": track.get("tracking_failures"), "lost_frames": track.get("lost_frames"),
                "prior_frames": 0 if out.prior_indices is None else len(out.prior_indices), "fps_end_to_end": res.fps_end_to_end, "wall_s": wall,
            }
            rows.append(row)
            print(f"  {seq_name:20s} stride {stride}  {name:14s} {row['frames']:4d} frames  {row['keyframes']:3d} kf  "
                  f"ATE {'    n/a' if err is None else f'{err:7.2f}'} cm  failures {row['tracking_failures']}  lost {row['lost_frames']}  "
                  f"prior {row['prior_frames']}  {row['fps_end_to_end']:5.1f} fps", flush=True)
    write_json(args.out, {"threads": 1, "load_average": load_average(), "rows": rows})


if __name__ == "__main__":
    main()
