"""NI-SLAM speed: per-stage A/B against another checkout, and the speed/accuracy trade-off of the image sizes.

Three commands (one torch thread unless ``--threads``; the machine's load is printed with each):

    # one run, as JSON: frames/s end to end, compute, front-end; ms per frame of each stage
    python scripts/bench_speed.py run tum_fr1_xyz [--frames N] [--set '{"pixel_stride": 2}']
    # this checkout against another one (e.g. main's worktree), run alternately in subprocesses
    python scripts/bench_speed.py ab --other ../main [--rounds 3] [--sequences tum_fr1_xyz,synthetic-orbit-0]
    # the same, frame by frame in one process: both checkouts' NISlam on the same decoded frames
    python scripts/bench_speed.py interleave --other ../main [--sequences tum_fr1_xyz,synthetic-orbit-0]
    # pixel_stride x orthographic size: ATE and frames/s at this checkout's code
    python scripts/bench_speed.py pareto [--strides 1,2] [--sizes 360x480,300x400,240x320]

Sequences are the names of real sequences under ``$TORCHSLAM_DATA`` (attitude from ground truth)
or ``synthetic-KIND-SEED`` (640 x 480, the IMU attitude; ``--synthetic-frames`` frames).

Front-end, as reported here: the per-frame tracking pipeline without the decode, the loop
closure and the end-of-run map, i.e. the stages ``backproject`` (attitude lookup, images to the
device, back-projection and grey re-sampling), ``kcc`` (``track_step``), ``fusion`` and
``keyframe`` (a new keyframe's map and filter). ``frames/s end-to-end`` is frames over the wall
time of ``run_sequence`` with the prefetching loader (decode overlaps on another thread), loop
closure and the final map included.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from _bench import data_root, load_average, write_json

FRONTEND_STAGES = ("backproject", "kcc", "fusion", "keyframe")
STAGES = (*FRONTEND_STAGES, "loop")


def _sequence(name: str, synthetic_frames: int, end: int | None):
    from torchslam.data.synthetic import SyntheticConfig, generate_sequence
    from torchslam.data.tum import TUMSequence

    if name.startswith("synthetic-"):
        _, kind, seed = name.split("-")
        frames = synthetic_frames if end is None else min(end, synthetic_frames)
        return generate_sequence(SyntheticConfig(frames=frames, trajectory=kind, seed=int(seed))), "imu"
    return TUMSequence(data_root() / name, prefetch=2, end=end), "groundtruth"


def run_case(name: str, overrides: dict, synthetic_frames: int = 150, end: int | None = None) -> dict:
    """Run NI-SLAM on one sequence; frame rates, per-stage ms per frame and ATE."""
    from torchslam.config import config_from_dict
    from torchslam.data import Trajectory
    from torchslam.eval import ate
    from torchslam.systems import run_sequence
    from torchslam.systems.nislam import NISlam, NISlamConfig

    seq, attitude = _sequence(name, synthetic_frames, end)
    cfg = config_from_dict(NISlamConfig, {"attitude": attitude, **overrides})
    res = run_sequence(NISlam(cfg), seq)
    n = max(res.frames_processed, 1)
    stage = {k: v / n for k, v in res.output.stage_ms.items()}
    frontend_ms = sum(stage.get(k, 0.0) for k in FRONTEND_STAGES)
    out = res.output
    reference = seq.groundtruth_raw if getattr(seq, "groundtruth_raw", None) is not None else seq.groundtruth
    a = ate(Trajectory(out.timestamps, out.T_wc), reference) if reference is not None else None
    return {
        "sequence": name, "overrides": overrides, "frames": res.frames_processed,
        "keyframes": len(out.keyframe_indices),
        "fps_end_to_end": res.fps_end_to_end, "fps_compute": res.fps_compute,
        "fps_frontend": 1000.0 / frontend_ms if frontend_ms > 0 else 0.0,
        "stage_ms_per_frame": stage, "ate_rmse_m": a.stats["rmse"] if a is not None else None,
    }


def _run_in(tree: Path, name: str, args) -> dict:
    """``run`` in a subprocess with ``tree`` first on the path (its torchslam)."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, str(Path(__file__).resolve()), "run", name, "--threads", str(args.threads),
           "--synthetic-frames", str(args.synthetic_frames), "--set", args.set]
    if args.frames:
        cmd += ["--frames", str(args.frames)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def ab(args) -> dict:
    """Alternate this checkout and ``--other`` per round and sequence; medians and ratios per stage."""
    here = Path(__file__).resolve().parents[1]
    trees = {"before": Path(args.other).resolve(), "after": here}
    runs: dict[str, dict[str, list[dict]]] = {}
    for r in range(args.rounds):
        for name in args.sequences.split(","):
            for label, tree in trees.items():
                row = _run_in(tree, name, args)
                runs.setdefault(name, {}).setdefault(label, []).append(row)
                print(f"  round {r} {name:22s} {label:6s} e2e {row['fps_end_to_end']:6.1f} fps  front-end "
                      f"{row['fps_frontend']:6.1f} fps  load {load_average()}", flush=True)
    table = {}
    for name, by in runs.items():
        med = {}
        for label, rows in by.items():
            m = {k: statistics.median(r["stage_ms_per_frame"].get(k, 0.0) for r in rows) for k in STAGES}
            m["fps_end_to_end"] = statistics.median(r["fps_end_to_end"] for r in rows)
            m["fps_frontend"] = statistics.median(r["fps_frontend"] for r in rows)
            m["ate_rmse_m"] = rows[-1]["ate_rmse_m"]
            med[label] = m
        table[name] = med
    print("\n| sequence | quantity | before | after | ratio |\n|---|---|---:|---:|---:|")
    for name, med in table.items():
        b, a = med["before"], med["after"]
        for k in STAGES:
            ratio = b[k] / a[k] if a[k] > 0 else float("nan")
            print(f"| {name} | {k} (ms/frame) | {b[k]:.2f} | {a[k]:.2f} | {ratio:.2f}x |")
        for k in ("fps_frontend", "fps_end_to_end"):
            print(f"| {name} | {k.replace('fps_', 'frames/s ').replace('_', '-')} | {b[k]:.1f} | {a[k]:.1f} | {a[k] / b[k]:.2f}x |")
        print(f"| {name} | ATE RMSE (cm) | {100 * b['ate_rmse_m']:.3f} | {100 * a['ate_rmse_m']:.3f} | |")
    return {"runs": runs, "medians": table}


def _load_tree(path: Path) -> dict:
    """Import ``path``'s torchslam and set its modules aside (``_use`` puts them back), so two checkouts share a process."""
    import importlib

    sys.path.insert(0, str(path))
    try:
        mods = {n: importlib.import_module(n) for n in
                ("torchslam.systems.nislam", "torchslam.config", "torchslam.data.tum", "torchslam.data.synthetic")}
    finally:
        sys.path.pop(0)
    tree = {k: sys.modules[k] for k in list(sys.modules) if k == "torchslam" or k.startswith("torchslam.")}
    for k in tree:
        del sys.modules[k]
    return {"mods": tree, **{n.rsplit(".", 1)[-1]: m for n, m in mods.items()}}


def _use(tree: dict) -> None:
    """Make ``tree``'s modules the imported torchslam (type hints and lazy imports look there)."""
    sys.modules.update(tree["mods"])


def interleave(args) -> dict:
    """Both checkouts' NISlam in one process on the same decoded frames, alternating frame by frame.

    Decode is excluded (the frames are read first); load drift hits both alike. Reports ms per
    frame of ``track`` and of ``finish``, the stages, and whether the trajectories are identical.
    """
    trees = {"before": _load_tree(Path(args.other).resolve()), "after": _load_tree(Path(__file__).resolve().parents[1])}
    result = {}
    for name in args.sequences.split(","):
        systems, frames = {}, {}
        for label, t in trees.items():
            _use(t)
            if name.startswith("synthetic-"):
                _, kind, seed = name.split("-")
                seq = t["synthetic"].generate_sequence(t["synthetic"].SyntheticConfig(frames=args.synthetic_frames, trajectory=kind, seed=int(seed)))
                attitude = "imu"
            else:
                seq = t["tum"].TUMSequence(data_root() / name, end=args.frames)
                attitude = "groundtruth"
            frames[label] = list(seq)
            cfg = t["config"].config_from_dict(t["nislam"].NISlamConfig, {"attitude": attitude, **json.loads(args.set)})
            systems[label] = t["nislam"].NISlam(cfg)
            systems[label].start(seq)
        track = {label: 0.0 for label in trees}
        for k in range(len(frames["after"])):
            for label, t in trees.items():
                _use(t)
                t0 = time.perf_counter()
                systems[label].track(frames[label][k])
                track[label] += time.perf_counter() - t0
        outputs, finish = {}, {}
        for label, t in trees.items():
            _use(t)
            t0 = time.perf_counter()
            outputs[label] = systems[label].finish()
            finish[label] = time.perf_counter() - t0
        n = len(frames["after"])
        same = torch.equal(outputs["before"].T_wc, outputs["after"].T_wc)
        row = {label: {"track_ms_per_frame": 1000 * track[label] / n, "finish_ms": 1000 * finish[label],
                       "stage_ms_per_frame": {k: v / n for k, v in systems[label].stage_ms.items()}} for label in trees}
        row.update(frames=n, identical_trajectories=same, load=load_average())
        result[name] = row
        b, a = row["before"], row["after"]
        print(f"{name}: {n} frames, identical trajectories: {same}, load {row['load']}")
        print(f"  track: {b['track_ms_per_frame']:.2f} -> {a['track_ms_per_frame']:.2f} ms/frame "
              f"({b['track_ms_per_frame'] / a['track_ms_per_frame']:.2f}x); finish {b['finish_ms']:.0f} -> {a['finish_ms']:.0f} ms")
        for k in STAGES:
            sb, sa = b["stage_ms_per_frame"].get(k, 0.0), a["stage_ms_per_frame"].get(k, 0.0)
            print(f"  {k:12s} {sb:7.2f} -> {sa:7.2f} ms/frame" + (f"  ({sb / sa:.2f}x)" if sa > 0 else ""))
    return result


def pareto(args) -> list[dict]:
    """ATE and frames/s for every (pixel_stride, orthographic size) at this checkout's code."""
    rows = []
    for stride in (int(s) for s in args.strides.split(",")):
        for size in args.sizes.split(","):
            h, w = (int(v) for v in size.split("x"))
            sets = {"pixel_stride": stride, "kcc": {"ortho_height": h, "ortho_width": w}}
            for name in args.sequences.split(","):
                row = run_case(name, sets, args.synthetic_frames, args.frames)
                row.update(pixel_stride=stride, ortho=size, load=load_average())
                rows.append(row)
                print(f"  stride {stride} {size:8s} {name:22s} ATE {100 * row['ate_rmse_m']:6.2f} cm  e2e "
                      f"{row['fps_end_to_end']:6.1f} fps  front-end {row['fps_frontend']:6.1f} fps", flush=True)
    names = args.sequences.split(",")
    print("\n| pixel_stride | ortho | " + " | ".join(f"{n} ATE (cm)" for n in names)
          + " | frames/s end-to-end (mean) | frames/s front-end (mean) |")
    print("|---|---|" + "---:|" * (len(names) + 2))
    for stride in (int(s) for s in args.strides.split(",")):
        for size in args.sizes.split(","):
            sel = [r for r in rows if r["pixel_stride"] == stride and r["ortho"] == size]
            ates = " | ".join(f"{100 * r['ate_rmse_m']:.2f}" for r in sel)
            e2e = statistics.mean(r["fps_end_to_end"] for r in sel)
            fe = statistics.mean(r["fps_frontend"] for r in sel)
            print(f"| {stride} | {size} | {ates} | {e2e:.1f} | {fe:.1f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    sub = ap.add_subparsers(dest="command", required=True)
    for cmd in ("run", "ab", "interleave", "pareto"):
        p = sub.add_parser(cmd)
        p.add_argument("--threads", type=int, default=1)
        p.add_argument("--frames", type=int, default=None, help="only the first N frames of each sequence")
        p.add_argument("--synthetic-frames", type=int, default=150)
        p.add_argument("--out", type=Path, default=None, help="write the result as JSON here")
        if cmd == "run":
            p.add_argument("sequence")
            p.add_argument("--set", default="{}", help="NISlamConfig overrides as JSON")
        else:
            p.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen,synthetic-orbit-0,synthetic-orbit-1,synthetic-orbit-2")
        if cmd in ("ab", "interleave"):
            p.add_argument("--other", required=True, help="the checkout to compare against (its repository root)")
            p.add_argument("--set", default="{}", help="NISlamConfig overrides as JSON")
        if cmd == "ab":
            p.add_argument("--rounds", type=int, default=3)
        if cmd == "pareto":
            p.add_argument("--strides", default="1,2")
            p.add_argument("--sizes", default="360x480,300x400,240x320")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.command == "run":
        result = run_case(args.sequence, json.loads(args.set), args.synthetic_frames, args.frames)
        result["load"] = load_average()
        print(json.dumps(result))
    else:
        print(f"load average (1, 5, 15 min): {load_average()}  threads: {args.threads}  {time.strftime('%H:%M:%S')}")
        result = {"ab": ab, "interleave": interleave, "pareto": pareto}[args.command](args)
        print(f"load average at the end: {load_average()}")
    write_json(args.out, result)


if __name__ == "__main__":
    main()
