"""Fast motion by frame skipping: every system on every n-th frame of the real sequences.

    python scripts/bench_fast_motion.py [--systems nislam,gcslam-sparse,gcslam-dense]
                                        [--strides hololens_dvmvs=2,3 tum_fr1_xyz=4,6 7scenes_redkitchen=4,8]
                                        [--blur [SEED:EXPOSURE ...]] [--gcslam-set KEY=VALUE ...]

``--blur`` adds (``--strides`` with no value: only) fast synthetic walks with motion blur: the
``loop`` trajectory at a 3.4 s period, 313 frames at 30 Hz (about 8 cm and 3.5 degrees between
frames, the fast HoloLens walk of issue 17), each frame's colour averaged over ``EXPOSURE``
seconds of the motion (``SyntheticConfig.exposure``, 12 renders); seeds below 100 are the tuning
split, from 100 the held-out one. Each sequence is rendered once to a temporary TUM folder.

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
import tempfile
import time
from pathlib import Path

import torch

from _bench import RESULTS, SYSTEMS, ate_cm, data_root, load_average, system_by_name, write_json
from torchslam.config import parse_overrides
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
from torchslam.data.tum import TUMSequence
from torchslam.systems import run_sequence

DEFAULT_STRIDES = ("hololens_dvmvs=1,2,3", "tum_fr1_xyz=4,6", "7scenes_redkitchen=4,8")
DEFAULT_BLUR = ("7:0", "7:0.01", "7:0.02", "107:0", "107:0.01", "107:0.02")
FAST_WALK = dict(frames=313, trajectory="loop", period=3.4, exposure_samples=12)


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


def _seed_split(seed: int) -> str:
    """A synthetic seed's split: ``tuning`` below 100, ``held-out`` from 100."""
    return "tuning" if seed < 100 else "held-out"


def _real_split(sequence: str) -> str:
    """A shipped sequence's split: HoloLens is held out."""
    return "held-out" if sequence.startswith("hololens") else "tuning"


def _blur_cases(items: list[str], option: str = "--blur") -> list[tuple[int, float]]:
    """``SEED:EXPOSURE`` items as (seed, seconds); a bad one exits naming ``option``."""
    cases = []
    for item in items:
        seed, sep, exposure = item.partition(":")
        try:
            cases.append((int(seed), float(exposure)))
        except ValueError:
            raise SystemExit(f"{option}: expected SEED:EXPOSURE, got {item!r}") from None
        if not sep or cases[-1][1] < 0:
            raise SystemExit(f"{option}: expected SEED:EXPOSURE with EXPOSURE >= 0 seconds, got {item!r}")
    return cases


def _blurred_walks(cases: list[tuple[int, float]], folder: Path) -> list[tuple[str, str, Path, int]]:
    """Render each fast walk once to a TUM folder under ``folder``: ``(name, split, folder, stride 1)``."""
    out = []
    for seed, exposure in cases:
        cfg = SyntheticConfig(seed=seed, exposure=exposure, **FAST_WALK)
        name, split = f"fast-walk-{seed}-exposure{exposure:g}", _seed_split(seed)
        t0 = time.perf_counter()
        write_tum_folder(generate_sequence(cfg), folder / name)
        print(f"  rendered {name} ({split}) in {time.perf_counter() - t0:.0f} s", flush=True)
        out.append((name, split, folder / name, 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--strides", nargs="*", default=list(DEFAULT_STRIDES), metavar="SEQUENCE=N[,N...]")
    ap.add_argument("--blur", nargs="*", default=None, metavar="SEED:EXPOSURE",
                    help=f"also the blurred fast synthetic walks (default cases: {' '.join(DEFAULT_BLUR)})")
    ap.add_argument("--gcslam-set", dest="gcslam_set", action="append", default=[], metavar="KEY=VALUE",
                    help="a GC-SLAM setting for both GC-SLAM systems, e.g. orb_min_fast_threshold=20 (repeatable)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_fast_motion.json")
    args = ap.parse_args()
    gcslam_values = parse_overrides(args.gcslam_set)
    torch.set_num_threads(1)
    root = data_root()
    systems = args.systems.split(",")
    unknown = sorted(set(systems) - set(SYSTEMS))
    if unknown:  # before any run
        raise SystemExit(f"--systems: unknown {', '.join(unknown)} (known: {', '.join(SYSTEMS)})")
    blur = _blur_cases(args.blur or list(DEFAULT_BLUR)) if args.blur is not None else []
    cases = []
    for seq_name, stride in _strides(args.strides):
        if not (root / seq_name / "rgb.txt").is_file():
            print(f"  {seq_name}: not under {root}, skipped")
            continue
        cases.append((seq_name, _real_split(seq_name), root / seq_name, stride))
    tmp = tempfile.TemporaryDirectory(prefix="torchslam-fast-walk-")
    cases += _blurred_walks(blur, Path(tmp.name))
    rows = []
    for seq_name, split, folder, stride in cases:
        for name in systems:
            seq = TUMSequence(folder, stride=stride, prefetch=2)
            t0 = time.perf_counter()
            res = run_sequence(system_by_name(name, **({} if name == "nislam" else gcslam_values)), seq)
            wall = time.perf_counter() - t0
            out = res.output
            err = ate_cm(out, seq)
            track = out.metrics.get("tracking", {})
            row = {
                "sequence": seq_name, "split": split, "stride": stride, "system": name, "frames": res.frames_processed,
                "keyframes": len(out.keyframe_indices), "ate_rmse_cm": err,
                "tracking_failures": track.get("tracking_failures"), "lost_frames": track.get("lost_frames"),
                "prior_frames": 0 if out.prior_indices is None else len(out.prior_indices), "fps_end_to_end": res.fps_end_to_end, "wall_s": wall,
            }
            rows.append(row)
            print(f"  {seq_name:20s} stride {stride}  {name:14s} {row['frames']:4d} frames  {row['keyframes']:3d} kf  "
                  f"ATE {'    n/a' if err is None else f'{err:7.2f}'} cm  failures {row['tracking_failures']}  lost {row['lost_frames']}  "
                  f"prior {row['prior_frames']}  {row['fps_end_to_end']:5.1f} fps", flush=True)
    tmp.cleanup()
    write_json(args.out, {"threads": 1, "load_average": load_average(), "fast_walk": FAST_WALK, "gcslam_set": args.gcslam_set,
                          "rows": rows})


if __name__ == "__main__":
    main()
