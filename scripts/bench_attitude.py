"""The simulated attitude's tilt error with and without acceleration compensation, over IMU noise draws.

For each trajectory (the shipped real sequences' ground truth and the long synthetic loop of
``bench_loops.py``) and each noise draw (``simulated_attitude``'s seed, NISlamConfig.sim_seed),
the attitude filter runs as NI-SLAM's ``attitude=simulated`` does. ``imu.AccelerationCompensation``
then runs its tilt correction again, fed the true positions frame by frame. That is an upper
bound for what NI-SLAM's tracked positions give (``bench_nislam.py`` measures those end to end).
Reports the tilt RMS against the ground truth at the frames, per draw and on average. The
compensation removes a deterministic error (the body's acceleration leaking into the gravity
direction) from a random one (the gyro bias), so a single draw can go either way.

    python scripts/bench_attitude.py [--draws 12] [--sequences tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs,long-loop]

Writes ``scripts/results/bench_attitude.json`` (``--out``) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import numpy as np
import torch

from _bench import RESULTS, data_root, write_json
from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data.tum import TUMSequence
from torchslam.environment import environment_info
from torchslam.imu import attitude_errors, interpolate_rotations, simulated_attitude
from torchslam.imu.compensation import AccelerationCompensation
from torchslam.systems.nislam import NISlamConfig
from torchslam.systems.nislam.attitude import gravity_vector

F64 = torch.float64


def _trajectory(name: str):
    """(ground truth, frame times, world gravity) of a shipped sequence or the long synthetic loop."""
    if name == "long-loop":
        frames = 1500
        seq = generate_sequence(SyntheticConfig(frames=frames, period=frames / 30.0 * 0.9, trajectory="loop", seed=0,
                                                width=64, height=48))
        return seq.groundtruth, seq.groundtruth.timestamps.to(F64), torch.tensor([0.0, 0.0, -9.81], dtype=F64)
    seq = TUMSequence(data_root() / name)
    gt = seq.groundtruth_raw if getattr(seq, "groundtruth_raw", None) is not None else seq.groundtruth
    return gt, seq.groundtruth.timestamps.to(F64), gravity_vector(NISlamConfig().gravity, gt)


def tilt_rms(name: str, draws: int, half_window: int) -> list[dict]:
    """Per draw: tilt RMS (degrees) of the plain and the compensated attitude at the frame times."""
    gt, times, g = _trajectory(name)
    up = -g / g.norm()
    tg = gt.timestamps.to(F64)
    times = times[(times >= tg[0]) & (times <= tg[-1])]
    pg = gt.T_wc[:, :3, 3].to(F64).numpy()
    positions = torch.from_numpy(np.stack([np.interp(times.numpy(), tg.numpy(), pg[:, i]) for i in range(3)], axis=1))
    R_true, _ = interpolate_rotations(tg, gt.T_wc[:, :3, :3].to(F64), times, 1.0)
    rows = []
    for draw in range(draws):
        stream = simulated_attitude(gt, gravity_w=g, seed=draw)
        R, ok = stream.at(times)
        comp = AccelerationCompensation(stream, half_window)
        R_comp = []
        for k in range(len(times)):
            R_comp.append(comp.correction(float(times[k])) @ R[k])
            comp.observe(float(times[k]), positions[k])
        plain, _ = attitude_errors(R, R_true, up=up)
        compensated, _ = attitude_errors(torch.stack(R_comp), R_true, up=up)
        rms = lambda x: math.degrees(float(x.square().mean().sqrt()))  # noqa: E731
        rows.append({"sequence": name, "draw": draw, "frames": len(times), "tilt_rms_deg_plain": rms(plain),
                     "tilt_rms_deg_compensated": rms(compensated)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=12, help="IMU noise draws (seeds 0 .. N-1)")
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs,long-loop",
                    help="shipped sequence folders under $TORCHSLAM_DATA and/or long-loop")
    ap.add_argument("--half-window", type=int, default=NISlamConfig().accel_window, help="accel_window h")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_attitude.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows, lines = [], ["| trajectory | frames | tilt RMS without → with (mean over draws, °) | draws better | draw 0 |",
                       "|---|---:|---|---:|---|"]
    for name in args.sequences.split(","):
        if name != "long-loop" and not (data_root() / name / "rgb.txt").is_file():
            print(f"skipped {name}: not under {data_root()}")
            continue
        r = tilt_rms(name, args.draws, args.half_window)
        rows += r
        p = [x["tilt_rms_deg_plain"] for x in r]
        c = [x["tilt_rms_deg_compensated"] for x in r]
        better = sum(b < a for a, b in zip(p, c))
        lines.append(f"| {name} | {r[0]['frames']} | {statistics.mean(p):.3f} → {statistics.mean(c):.3f} | "
                     f"{better} / {len(r)} | {p[0]:.3f} → {c[0]:.3f} |")
        print(lines[-1], flush=True)
    write_json(args.out, {"machine": environment_info(), "draws": args.draws, "half_window": args.half_window, "rows": rows})
    print("\n".join(lines))


if __name__ == "__main__":
    main()
