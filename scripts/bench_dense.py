"""GC-SLAM dense front-end: this checkout against another one, frame by frame in one process.

    python scripts/bench_dense.py --other /work/main [--sequences tum_fr1_xyz,synthetic-orbit-0] [--frames N]

Both checkouts' GCSlam (``frontend=dense``, optimisation inline so both runs are deterministic)
track the same decoded frames, alternating frame by frame, so load drift hits both alike (the
decode is excluded). One torch thread unless ``--threads``. Reports, per sequence and checkout:
ms per frame of ``track`` and of each stage, frames/s of ``track`` plus ``finish``, the ATE RMSE
and whether the trajectories are identical.

Sequences are names under ``$TORCHSLAM_DATA`` or ``synthetic-KIND-SEED`` (``--synthetic-frames``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from _bench import data_root, load_average, load_tree, use_tree, write_json

STAGES = ("dense_preparation", "registration", "keyframe_decision", "orb_extraction", "keyframe_insertion")




def _sequence(t: dict, name: str, frames: int | None, synthetic_frames: int):
    if name.startswith("synthetic-"):
        _, kind, seed = name.split("-")
        syn = t["torchslam.data.synthetic"]
        return syn.generate_sequence(syn.SyntheticConfig(frames=synthetic_frames, trajectory=kind, seed=int(seed)))
    tum = t["torchslam.data.tum"]
    if frames is not None and frames >= len(tum.TUMSequence(data_root() / name)):
        frames = None
    return tum.TUMSequence(data_root() / name, end=frames)


def _ate(t: dict, seq, out) -> float | None:
    ref = getattr(seq, "groundtruth_raw", None) or seq.groundtruth
    if ref is None:
        return None
    return float(t["torchslam.eval"].ate(t["torchslam.data"].Trajectory(out.timestamps, out.T_wc), ref).stats["rmse"])


def compare(name: str, trees: dict, args) -> dict:
    systems, frames, seqs = {}, {}, {}
    for label, t in trees.items():
        use_tree(t)
        seq = _sequence(t, name, args.frames, args.synthetic_frames)
        frames[label], seqs[label] = list(seq), seq
        gc = t["torchslam.systems.gcslam"]
        overrides = {"frontend": "dense", "threaded": False, **json.loads(args.set.get(label, "{}") if isinstance(args.set, dict) else args.set)}
        systems[label] = gc.GCSlam(t["torchslam.config"].config_from_dict(gc.GCSlamConfig, overrides))
        systems[label].start(seq)
    n = len(frames["after"])
    track = dict.fromkeys(trees, 0.0)
    for k in range(n):
        for label, t in trees.items():
            use_tree(t)
            t0 = time.perf_counter()
            systems[label].track(frames[label][k])
            track[label] += time.perf_counter() - t0
    row = {}
    outs = {}
    for label, t in trees.items():
        use_tree(t)
        t0 = time.perf_counter()
        outs[label] = systems[label].finish()
        fin = time.perf_counter() - t0
        row[label] = {
            "track_ms_per_frame": 1000 * track[label] / n, "finish_ms": 1000 * fin,
            "fps": n / (track[label] + fin),
            "stage_ms_per_frame": {s: v / n for s, v in systems[label].stage_ms.items()},
            "keyframes": len(outs[label].keyframe_indices),
            "ate_rmse_cm": (lambda a: None if a is None else 100 * a)(_ate(t, seqs[label], outs[label])),
        }
    same = outs["before"].T_wc.shape == outs["after"].T_wc.shape and torch.equal(outs["before"].T_wc, outs["after"].T_wc)
    row.update(frames=n, identical_trajectories=same, load=load_average())
    b, a = row["before"], row["after"]
    fmt = lambda v: "nan" if v is None else f"{v:.3f}"
    print(f"{name}: {n} frames, identical: {same}, load {row['load']}")
    print(f"  track {b['track_ms_per_frame']:.2f} -> {a['track_ms_per_frame']:.2f} ms/frame "
          f"({b['track_ms_per_frame'] / a['track_ms_per_frame']:.2f}x); fps {b['fps']:.1f} -> {a['fps']:.1f}; "
          f"ATE {fmt(b['ate_rmse_cm'])} -> {fmt(a['ate_rmse_cm'])} cm; keyframes {b['keyframes']} -> {a['keyframes']}")
    for s in STAGES:
        sb, sa = b["stage_ms_per_frame"].get(s, 0.0), a["stage_ms_per_frame"].get(s, 0.0)
        print(f"  {s:20s} {sb:7.2f} -> {sa:7.2f} ms/frame" + (f"  ({sb / sa:.2f}x)" if sa > 0 else ""), flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--other", required=True, help="the checkout to compare against (its repository root)")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs,synthetic-orbit-0")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames of each real sequence")
    ap.add_argument("--synthetic-frames", type=int, default=150)
    ap.add_argument("--set", default="{}", help="GCSlamConfig overrides for this checkout as JSON")
    ap.add_argument("--set-other", default="{}", help="GCSlamConfig overrides for the other checkout as JSON")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="write the result as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.set = {"after": args.set, "before": args.set_other}
    trees = {"before": load_tree(Path(args.other).resolve()), "after": load_tree(Path(__file__).resolve().parents[1])}
    print(f"load average (1, 5, 15 min): {load_average()}  threads: {args.threads}  {time.strftime('%H:%M:%S')}")
    result = {name: compare(name, trees, args) for name in args.sequences.split(",")}
    print(f"load average at the end: {load_average()}")
    write_json(args.out, result)


if __name__ == "__main__":
    main()
