"""NI-SLAM: this checkout against another, frame by frame in one process.

Both checkouts' NISlam (default settings unless ``--set``) run on the same decoded frames,
alternating frame by frame, so the machine's load drift hits both alike. Reports ms per frame
of ``track`` and of each stage (``stage_ms``: backproject, kcc, fusion, keyframe, loop), the
ratio before/after, the ATE of each and the largest position difference between the two
trajectories (0 for a change that keeps the arithmetic).

    python scripts/bench_nislam_ab.py --other /work/main [--sequences tum_fr1_xyz,7scenes_redkitchen] \
        [--frames 300] [--repeat 1] [--set '{"kcc": {"subpixel": "none"}}'] [--set-other '{}']

Sequences are real sequences under ``$TORCHSLAM_DATA`` or ``synthetic-KIND-SEED``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from _bench import data_root, load_average, load_tree, print_stage_ratios, tree_ate_cm, use_tree, write_json

NISLAM_MODULES = ("torchslam.systems.nislam", "torchslam.config", "torchslam.data.tum", "torchslam.data.synthetic",
                  "torchslam.data", "torchslam.eval")


def _sequence(t: dict, name: str, frames: int):
    if name.startswith("synthetic-"):
        _, kind, seed = name.split("-")
        syn = t["torchslam.data.synthetic"]
        return syn.generate_sequence(syn.SyntheticConfig(frames=frames, trajectory=kind, seed=int(seed)))
    tum = t["torchslam.data.tum"].TUMSequence
    seq = tum(data_root() / name)
    return tum(data_root() / name, end=frames) if len(seq) > frames else seq


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", required=True, help="the other checkout (before)")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=1, help="runs of each sequence (times summed over them)")
    ap.add_argument("--set", default="{}", help="JSON overrides for this checkout (after)")
    ap.add_argument("--set-other", default="{}", help="JSON overrides for the other checkout (before)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    trees = {"before": load_tree(Path(args.other).resolve(), NISLAM_MODULES),
             "after": load_tree(Path(__file__).resolve().parents[1], NISLAM_MODULES)}
    sets = {"before": json.loads(args.set_other), "after": json.loads(args.set)}
    rows = {}
    print(f"load {load_average()}, torch threads {torch.get_num_threads()}")
    for name in args.sequences.split(","):
        track = {label: 0.0 for label in trees}
        stage = {label: {} for label in trees}
        outs, seqs, n_total = {}, {}, 0
        for _ in range(args.repeat):
            systems, frames = {}, {}
            for label, t in trees.items():
                use_tree(t)
                seqs[label] = _sequence(t, name, args.frames)
                frames[label] = list(seqs[label])
                ni = t["torchslam.systems.nislam"]
                cfg = t["torchslam.config"].config_from_dict(ni.NISlamConfig, sets[label])
                systems[label] = ni.NISlam(cfg)
                systems[label].start(seqs[label])
            n = len(frames["after"])
            n_total += n
            for k in range(n):
                order = list(trees.items()) if k % 2 == 0 else list(trees.items())[::-1]
                for label, t in order:
                    use_tree(t)
                    t0 = time.perf_counter()
                    systems[label].track(frames[label][k])
                    track[label] += time.perf_counter() - t0
            for label, t in trees.items():
                use_tree(t)
                outs[label] = systems[label].finish()
                for key, v in systems[label].stage_ms.items():
                    stage[label][key] = stage[label].get(key, 0.0) + v
        row = {"frames": n_total, "load": load_average()}
        for label, t in trees.items():
            use_tree(t)
            out, seq = outs[label], seqs[label]
            ate_cm = tree_ate_cm(t, out, seq)
            row[label] = {"track_ms": 1000 * track[label] / n_total, "fps_track": n_total / track[label],
                          "ate_cm": ate_cm, "keyframes": len(out.keyframe_indices),
                          "stage_ms": {k: v / n_total for k, v in stage[label].items()}}
        pb, pa = outs["before"].T_wc[:, :3, 3].double(), outs["after"].T_wc[:, :3, 3].double()
        row["max_position_diff_m"] = float((pb - pa).abs().max()) if pb.shape == pa.shape else None
        rows[name] = row
        b, a = row["before"], row["after"]
        print(f"{name}: {n_total} frames, load {row['load']}")
        print(f"  track {b['track_ms']:.1f} -> {a['track_ms']:.1f} ms/frame ({b['track_ms'] / a['track_ms']:.2f}x)  "
              f"ATE {b['ate_cm']:.3f} -> {a['ate_cm']:.3f} cm  kf {b['keyframes']} -> {a['keyframes']}  "
              f"max position diff {row['max_position_diff_m']}")
        print_stage_ratios(b["stage_ms"], a["stage_ms"], 12)
    write_json(args.out, rows)


if __name__ == "__main__":
    main()
