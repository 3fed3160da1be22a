"""Write a there-and-back stand-in for a long sequence that revisits its places.

The shipped sequences are short (50-300 frames) and never come back to where they started,
while the long ones the issues measure on (all 798 frames of TUM fr1/xyz, which sweeps back and
forth over one desk) do, so their loop closure is never exercised on real images here. This
script plays a TUM-layout sequence forward, backward, forward and backward again (frames 0..n-1,
n-2..0, 1..n-1, n-2..0: about 4 n frames) into a new folder of symbolic links to the original
images, re-timed at the original frame rate, with the ground truth of each source frame at its
new stamp. Colour and depth share each new stamp (the original pairs' offset is dropped), and
the ground truth written there is the pose at the source frame's depth instant, where its
geometry was taken (TUM fr1 takes colour about 15 ms after depth; at the camera's speed the
colour instant's pose would put millimetres of timing error into every frame). There is no
accelerometer file, so use ``attitude=groundtruth`` or ``simulated`` on it. Its
``calibration.txt`` is the source's camera with ``readout 0`` (``write_calibration``).

The images are real; the motion reverses at each end within one frame, which the constant-
velocity prediction misses once. Revisited places show the very same images, so the loops it
offers are easier to verify than a real revisit's: read its figures as whether loops close and
bound the drift, not as a real sequence's accuracy.

Usage::

    python scripts/make_revisit.py tum_fr1_xyz --out /tmp/revisit   # -> /tmp/revisit/tum_fr1_xyz_palindrome
    torchslam run --system nislam --data /tmp/revisit/tum_fr1_xyz_palindrome --set attitude=groundtruth
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

from _bench import data_root
from torchslam.data import Trajectory, TUMSequence
from torchslam.data.calibration import CALIBRATION_FILE, READOUT_KEYWORD
from torchslam.data.trajectory import write_tum_trajectory


def revisit_order(n: int) -> list[int]:
    """Frame indices forward, backward, forward, backward (no frame repeated at a turn)."""
    if n < 2:
        raise ValueError(f"a sequence of {n} frame(s) cannot be played back and forth")
    back = list(range(n - 2, -1, -1))
    return list(range(n)) + back + list(range(1, n)) + back


def write_calibration(src: Path, seq: TUMSequence, path: Path) -> None:
    """The stand-in's ``calibration.txt``: the source's camera as it reads it, with ``readout 0``.

    Played backward, a frame's rows were read while the camera moved the other way to how the
    stand-in's stamps say it moves, so a rolling-shutter model (GC-SLAM's ``readout_time``, whose
    ``auto`` takes a Kinect's 0.03 s from a name like the source's) would double the distortion
    on every backward leg instead of undoing it: the stand-in declares a global shutter.
    """
    calib = src / CALIBRATION_FILE
    if calib.is_file():  # its own lines (the colour camera's among them), any readout line left out
        lines = [line for line in calib.read_text().splitlines() if line.split()[:1] != [READOUT_KEYWORD]]
    else:  # the folder-name preset the source was read with
        cam = seq.camera
        values = [cam.fx, cam.fy, cam.cx, cam.cy, seq.depth_scale, cam.width, cam.height, *(cam.distortion or ())]
        lines = [f"# fx fy cx cy depth_scale width height [distortion]  ({seq.calibration_source} of {src.name})",
                 " ".join(repr(v) for v in values)]
    lines += ["# there-and-back stand-in: half its frames play backward, so no rolling-shutter model applies",
              f"{READOUT_KEYWORD} 0"]
    path.write_text("\n".join(lines) + "\n")


def write_revisit(src: Path, dst: Path, fps: float = 30.0, start: float = 1.0e9) -> int:
    """Write ``dst`` (created, must be empty or missing) from the TUM folder ``src``; return its frame count."""
    seq = TUMSequence(src)
    reference = seq.groundtruth_raw if seq.groundtruth_raw is not None else seq.groundtruth
    if reference is None:
        raise SystemExit(f"{src}: no ground truth; the stand-in needs it for every frame")
    # The pose at each frame's depth instant (its geometry), bridging gaps as the reader does.
    T_all, valid = reference.interpolate(seq.depth_timestamps.to(torch.float64), max_gap=seq.gt_max_gap)
    if not bool(valid.all()):
        missing = int((~valid).sum())
        raise SystemExit(f"{src}: {missing} frame(s) have no ground truth at their depth instant; the stand-in needs it for every frame")
    if dst.exists() and any(dst.iterdir()):
        raise SystemExit(f"{dst}: exists and is not empty")
    (dst / "rgb").mkdir(parents=True, exist_ok=True)
    (dst / "depth").mkdir(exist_ok=True)
    write_calibration(src, seq, dst / "calibration.txt")
    order = revisit_order(len(seq))
    times = start + torch.arange(len(order), dtype=torch.float64) / fps
    rgb_lines, depth_lines = ["# colour images (there-and-back stand-in)"], ["# depth maps"]
    for t, i in zip(times.tolist(), order):
        rgb_name = f"rgb/{t:.6f}{Path(seq.rgb_paths[i]).suffix}"
        depth_name = f"depth/{t:.6f}{Path(seq.depth_paths[i]).suffix}"
        os.symlink(Path(seq.rgb_paths[i]).resolve(), dst / rgb_name)
        os.symlink(Path(seq.depth_paths[i]).resolve(), dst / depth_name)
        rgb_lines.append(f"{t:.6f} {rgb_name}")
        depth_lines.append(f"{t:.6f} {depth_name}")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines)):
        (dst / name).write_text("\n".join(lines) + "\n")
    write_tum_trajectory(dst / "groundtruth.txt", Trajectory(times, T_all[order]), header="ground truth (there-and-back stand-in)")
    return len(order)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", help="sequence folder names under --data")
    ap.add_argument("--data", type=Path, default=data_root(), help="folder holding the sequences (default $TORCHSLAM_DATA)")
    ap.add_argument("--out", type=Path, required=True, help="folder to write <name>_palindrome into (outside the project)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate of the new stamps")
    args = ap.parse_args(argv)
    if args.fps <= 0 or not np.isfinite(args.fps):
        ap.error(f"--fps: expected a positive frame rate, got {args.fps}")
    for name in args.sequences:
        src = args.data / name
        if not (src / "rgb.txt").is_file():
            ap.error(f"{src}: no rgb.txt (not a TUM-layout sequence)")
        n = write_revisit(src, args.out / f"{name}_palindrome", args.fps)
        print(f"{args.out / (name + '_palindrome')}: {n} frames", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
