"""How far KCC's translation falls short of the truth on real frame pairs, with and without a window.

For frame pairs ``(i, i + gap)`` of each sequence, the frame is matched against a keyframe made
from frame ``i`` with the ground-truth relative rotation (so only the front-end's translation is
measured), and the estimated camera translation is compared with the ground truth's; with
``--centers`` the frame's orthographic image is also centred on the true translation plus
Gaussian noise of each given standard deviation (``track_step``'s ``center``, a prediction that
errs by that much; "axis" is the frame's own optical axis, the paper's). The
"slope" per axis is the least-squares factor ``e ≈ slope * d`` of the error ``e`` on the true
displacement ``d``: -0.10 means the estimate is 10 % short. Writes
``scripts/results/bench_window.json`` and prints a markdown table.

    python scripts/bench_window.py                      # gaps 2,5,8,12 and 15,25
    python scripts/bench_window.py --sequences tum_fr1_xyz --gaps 2,5
    python scripts/bench_window.py --windows none --centers axis,0.005,0.015 --out scripts/results/nislam_center
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

import torch

from _bench import RESULTS
from torchslam.data.tum import TUMSequence
from torchslam.environment import environment_info
from torchslam.geometry import se3_inverse, undistorted_rays
from torchslam.kcc import KCCConfig, choose_resolution, keyframe_filter, keyframe_map, orthographic_project, rgbd_to_points, track_step
from torchslam.systems.nislam import NISlamConfig


def pair_errors(
    seq: TUMSequence, cfg: KCCConfig, gaps: list[int], every: int, center_noise: float | None = None, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """(errors (P, 3), true displacements (P, 3)) of the camera translation, keyframe frame, metres.

    ``center_noise``: None centres each frame's image on its axis; a number centres it on the
    true content translation plus that much Gaussian noise per axis, metres (seeded).
    """
    gen = torch.Generator().manual_seed(seed)
    gt = seq.groundtruth_raw if seq.groundtruth_raw is not None else seq.groundtruth
    intr = seq.camera.as_tensor(torch.float32)[None]
    rays = undistorted_rays(seq.camera, torch.float32, step=1) if seq.camera.has_distortion else None
    size = (cfg.ortho_height, cfg.ortho_width)
    clouds: dict[int, tuple] = {}

    def cloud(i: int):
        if i not in clouds:
            f = seq[i]
            clouds[i] = (f.geometry_time, *rgbd_to_points(f.rgb[None], f.depth[None], intr, rays=rays))
        return clouds[i]

    errors, truth = [], []
    for i in range(0, len(seq) - max(gaps), every):
        t0, p0, g0, v0 = cloud(i)
        r = choose_resolution(p0, v0, size, cfg.coverage, cfg.sample_step)
        km = keyframe_map(orthographic_project(p0, g0, v0, None, r, size))
        filt = keyframe_filter(km, cfg)
        for gap in gaps:
            t1, p1, g1, v1 = cloud(i + gap)
            T, ok = gt.interpolate(torch.tensor([t0, t1], dtype=torch.float64))
            if not bool(ok.all()):
                continue
            rel = se3_inverse(T[0]) @ T[1]
            center = None
            if center_noise is not None:  # the content moved by minus the camera's displacement
                noise = center_noise * torch.randn(2, generator=gen, dtype=torch.float64)
                center = (-rel[:2, 3] + noise)[None].float()
            res = track_step(p1, g1, v1, rel[:3, :3][None].float(), km, filt, r, cfg, center=center)
            errors.append(-res.t_content[0].double() - rel[:3, 3])
            truth.append(rel[:3, 3])
    return torch.stack(errors), torch.stack(truth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.environ.get("TORCHSLAM_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data")))
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs")
    ap.add_argument("--gaps", default="2,5,8,12;15,25", help="semicolon-separated groups of comma-separated frame gaps")
    ap.add_argument("--windows", default="none,hann")
    ap.add_argument("--every", type=int, default=9, help="a keyframe every this many frames")
    ap.add_argument("--centers", default="axis", help="comma-separated: axis, or the noise (m) of a centre on the truth")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for name in args.sequences.split(","):
        root = Path(args.data) / name
        if not (root / "rgb.txt").is_file():
            print(f"skipping {name}: no {root / 'rgb.txt'}")
            continue
        seq = TUMSequence(root)
        for group in args.gaps.split(";"):
            gaps = [int(g) for g in group.split(",")]
            if max(gaps) >= len(seq):
                continue
            for window in args.windows.split(","):
                cfg = replace(NISlamConfig().kcc, window=window)  # NI-SLAM's defaults but the window
                for center in args.centers.split(","):
                    noise = None if center == "axis" else float(center)
                    e, d = pair_errors(seq, cfg, gaps, args.every, noise)
                    slope = ((e * d).sum(0) / d.square().sum(0)).tolist()
                    row = {"sequence": name, "gaps": gaps, "window": window, "center": center, "pairs": len(e),
                           "slope_xyz": slope, "median_abs_error_mm": (1000 * e.abs().median(0).values).tolist(),
                           "rms_error_mm": (1000 * e.square().mean(0).sqrt()).tolist()}
                    rows.append(row)
                    print(f"  {name} gaps {group} window {window} center {center}: slope {slope[0]:+.3f} {slope[1]:+.3f} {slope[2]:+.3f}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_window.json").write_text(json.dumps({"machine": environment_info(), "rows": rows}, indent=2) + "\n")
    print("\n| sequence | frame gaps | window | centre | pairs | slope x | slope y | slope z | median abs error x, y, z (mm) | RMS error x, y, z (mm) |")
    print("|---|---|---|---|---:|---:|---:|---:|---|---|")
    for r in rows:
        sx, sy, sz = r["slope_xyz"]
        med = ", ".join(f"{v:.1f}" for v in r["median_abs_error_mm"])
        rms = ", ".join(f"{v:.1f}" for v in r["rms_error_mm"])
        print(f"| {r['sequence']} | {','.join(map(str, r['gaps']))} | {r['window']} | {r['center']} | {r['pairs']} | {sx:+.3f} | {sy:+.3f} | {sz:+.3f} | {med} | {rms} |")


if __name__ == "__main__":
    main()
