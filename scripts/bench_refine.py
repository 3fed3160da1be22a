"""How well ``kcc.refine_against_map`` measures rotation: frame pairs refined from a known error, against ground truth.

For frames ``i`` and ``i + gap`` of a sequence (every 10th ``i``), frame ``i``'s cloud makes an
orthographic map as a keyframe's is made, and frame ``i + gap``'s cloud is refined against it
from the true relative pose turned by ``--start-deg`` about a random axis (0: from the truth, which
shows where the cost's minimum lies). The clouds are NI-SLAM's own (undistorted rays, grey at the
depth instant). Prints the RMS, median and largest rotation error per sequence and gap, and the
time per refinement; writes ``scripts/results/bench_refine.json`` (``--out``). This is what
``loop.visual_rotation_sigma_deg`` was set from (the real tuning sequences).

    python scripts/bench_refine.py                       # fr1/xyz and 7-Scenes, gaps 15 and 45, from the truth
    python scripts/bench_refine.py --start-deg 0.5 --sequences hololens_dvmvs
    python scripts/bench_refine.py --synthetic 0,1,2,3   # synthetic seeds (320 x 240, depth noise) instead
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import torch

from _bench import RESULTS, data_root, write_json
from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data.tum import TUMSequence
from torchslam.environment import environment_info
from torchslam.geometry import se3_inverse, so3_exp, so3_log
from torchslam.kcc import choose_resolution, keyframe_map, orthographic_project, refine_against_map
from torchslam.systems.nislam import NISlam, NISlamConfig
from torchslam.systems.nislam.step import backproject


def pair_errors(seq, name: str, gaps: list[int], start_deg: float, seed: int = 0) -> list[dict]:
    """Rotation errors (degrees) of the refinement on the pairs of ``seq``, per gap."""
    system = NISlam(config_from_dict(NISlamConfig, {"attitude": "groundtruth"}))
    system.start(seq)
    frames = list(seq)
    size = (system.cfg.kcc.ortho_height, system.cfg.kcc.ortho_width)
    clouds: dict[int, object] = {}

    def cloud(i):
        if i not in clouds:
            inp = system._frame_input(frames[i])
            clouds[i] = None if inp is None else backproject([inp])[0]
        return clouds[i]

    g = torch.Generator().manual_seed(seed)
    rows = []
    for gap in gaps:
        errors, ms, failed = [], [], 0
        for i in range(0, len(frames) - gap, 10):
            ci, cj = cloud(i), cloud(i + gap)
            t = torch.tensor([frames[i].geometry_time, frames[i + gap].geometry_time], dtype=torch.float64)
            T_gt, ok = seq.groundtruth.interpolate(t)
            if ci is None or cj is None or not bool(ok.all()):
                continue
            T_true = se3_inverse(T_gt[0]) @ T_gt[1]
            r = choose_resolution(ci.points, ci.valid, size)
            kf_map = keyframe_map(orthographic_project(ci.points, ci.grey, ci.valid, None, r, size))
            axis = torch.randn(3, generator=g, dtype=torch.float64)
            T0 = T_true.clone()
            T0[:3, :3] = so3_exp(axis / axis.norm() * math.radians(start_deg)) @ T_true[:3, :3]
            t0 = time.perf_counter()
            res = refine_against_map(cj.points, cj.grey, cj.valid, kf_map, r, T0[None])
            ms.append(1000 * (time.perf_counter() - t0))
            if not bool(res.converged[0]):
                failed += 1
                continue
            errors.append(math.degrees(float(so3_log(res.T[0, :3, :3].T @ T_true[:3, :3]).norm())))
        row = {
            "sequence": name, "gap": gap, "start_deg": start_deg, "pairs": len(errors), "not_converged": failed,
            "rms_deg": math.sqrt(statistics.fmean(e * e for e in errors)) if errors else None,
            "median_deg": statistics.median(errors) if errors else None, "max_deg": max(errors) if errors else None,
            "ms_median": statistics.median(ms) if ms else None, "errors_deg": errors,
        }
        rows.append(row)
        if errors:
            print(f"| {name} | {gap} | {len(errors)} ({failed} not converged) | {row['rms_deg']:.3f} | {row['median_deg']:.3f} | "
                  f"{row['max_deg']:.3f} | {row['ms_median']:.0f} |", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen", help="shared sequences (comma-separated)")
    ap.add_argument("--synthetic", default=None, help="synthetic seeds instead of --sequences (comma-separated; 100-104 held out)")
    ap.add_argument("--gaps", default="15,45", help="frames between the two of a pair (comma-separated)")
    ap.add_argument("--start-deg", type=float, default=0.0, help="rotation error the refinement starts from, degrees")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--out", default=str(RESULTS / "bench_refine.json"), help="JSON output")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gaps = [int(x) for x in args.gaps.split(",")]
    print(f"start {args.start_deg} deg from the true relative pose; {args.threads} thread(s)")
    print("| sequence | gap (frames) | pairs | RMS (deg) | median | largest | ms per refinement |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    rows = []
    if args.synthetic:
        for seed in (int(s) for s in args.synthetic.split(",")):
            kind = ("handheld", "translate", "orbit", "loop")[seed % 4]
            seq = generate_sequence(SyntheticConfig(frames=200, trajectory=kind, seed=seed, width=320, height=240))
            rows += pair_errors(seq, f"synthetic-{kind}-{seed}", gaps, args.start_deg)
    else:
        root = data_root()
        for name in args.sequences.split(","):
            folder = Path(root) / name
            if not folder.is_dir():
                print(f"skipped {name}: no folder {folder}")
                continue
            rows += pair_errors(TUMSequence(folder), name, gaps, args.start_deg)
    write_json(Path(args.out), {"machine": environment_info(), "start_deg": args.start_deg, "rows": rows})


if __name__ == "__main__":
    main()
