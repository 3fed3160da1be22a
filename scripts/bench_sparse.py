"""GC-SLAM sparse front-end: this checkout against another, frame by frame in one process.

Both checkouts' GCSlam (sparse front-end, inline optimisation so no thread competes) run on the
same decoded frames, alternating frame by frame, so the machine's load drift hits both alike.
Reports ms per frame of ``track`` and of each stage, frames/s of ``track``, and the ATE of each.

    python scripts/bench_sparse.py --other /work/main [--sequences tum_fr1_xyz,synthetic-orbit-0] \
        [--frames 150] [--set '{"sparse": {"guided_radius": 0}}'] [--set-other '{}']

Sequences are real sequences under ``$TORCHSLAM_DATA`` or ``synthetic-KIND-SEED``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from _bench import data_root, load_average, load_tree, print_stage_ratios, tree_ate_cm, use_tree, write_json




def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", required=True, help="the other checkout (before)")
    ap.add_argument("--sequences", default="tum_fr1_xyz")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--set", default="{}", help="JSON overrides for this checkout (after)")
    ap.add_argument("--set-other", default="{}", help="JSON overrides for the other checkout (before)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    trees = {"before": load_tree(Path(args.other).resolve()), "after": load_tree(Path(__file__).resolve().parents[1])}
    sets = {"before": json.loads(args.set_other), "after": json.loads(args.set)}
    rows = {}
    print(f"load {load_average()}, torch threads {torch.get_num_threads()}")
    for name in args.sequences.split(","):
        systems, frames, seqs = {}, {}, {}
        for label, t in trees.items():
            use_tree(t)
            if name.startswith("synthetic-"):
                _, kind, seed = name.split("-")
                syn = t["torchslam.data.synthetic"]
                seq = syn.generate_sequence(syn.SyntheticConfig(frames=args.frames, trajectory=kind, seed=int(seed)))
            else:
                tum = t["torchslam.data.tum"].TUMSequence
                seq = tum(data_root() / name)
                if len(seq) > args.frames:
                    seq = tum(data_root() / name, end=args.frames)
            seqs[label] = seq
            frames[label] = list(seq)
            gc = t["torchslam.systems.gcslam"]
            cfg = t["torchslam.config"].config_from_dict(gc.GCSlamConfig, {"frontend": "sparse", "threaded": False, **sets[label]})
            systems[label] = gc.GCSlam(cfg)
            systems[label].start(seq)
        track = {label: 0.0 for label in trees}
        n = len(frames["after"])
        for k in range(n):
            for label, t in trees.items():
                use_tree(t)
                t0 = time.perf_counter()
                systems[label].track(frames[label][k])
                track[label] += time.perf_counter() - t0
        row = {"frames": n, "load": load_average()}
        for label, t in trees.items():
            use_tree(t)
            out = systems[label].finish()
            seq = seqs[label]
            ate_cm = tree_ate_cm(t, out, seq)
            st = systems[label].stage_ms
            row[label] = {"track_ms": 1000 * track[label] / n, "fps_track": n / track[label],
                          "ate_cm": ate_cm, "keyframes": len(out.keyframe_indices),
                          "counts": dict(systems[label].counts),
                          "stage_ms": {k: v / n for k, v in st.items()}}
            extra = getattr(systems[label].frontend, "counts", None)
            if extra is not None:
                row[label]["frontend_counts"] = dict(extra)
        rows[name] = row
        b, a = row["before"], row["after"]
        print(f"{name}: {n} frames, load {row['load']}")
        print(f"  track {b['track_ms']:.1f} -> {a['track_ms']:.1f} ms/frame ({b['track_ms'] / a['track_ms']:.2f}x)  "
              f"ATE {b['ate_cm']:.2f} -> {a['ate_cm']:.2f} cm  kf {b['keyframes']} -> {a['keyframes']}  "
              f"lost {b['counts'].get('lost_frames')} -> {a['counts'].get('lost_frames')}  {a.get('frontend_counts', '')}")
        print_stage_ratios(b["stage_ms"], a["stage_ms"], 20)
    write_json(args.out, rows)


if __name__ == "__main__":
    main()
