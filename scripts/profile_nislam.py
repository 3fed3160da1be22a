"""NI-SLAM per sub-step times inside the running system: wrappers around the sub-step functions.

Runs ``NISlam`` (default settings) through ``run_sequence`` on one real sequence and prints the
wall frame rate, ``stage_ms`` per frame, the minor page faults per frame and the ms per call of
each wrapped sub-step (ortho projection, channels, correlation and peak, depth translation,
back-projection and grey re-sampling, fusion). Times are in context (caches, allocator and page
faults as a run sees them), not isolated; compare two checkouts with ``bench_nislam_ab.py``.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python scripts/profile_nislam.py tum_fr1_xyz
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import time

import torch

import torchslam.kcc.correlator as co
import torchslam.kcc.frontend as fe
import torchslam.kcc.ortho as orm
import torchslam.systems.nislam.step as st
import torchslam.systems.nislam.system as sy
from _bench import data_root
from torchslam.config import config_from_dict
from torchslam.data.tum import TUMSequence
from torchslam.systems import run_sequence
from torchslam.systems.nislam import NISlam, NISlamConfig

TOTAL: dict[str, float] = collections.defaultdict(float)
CALLS: collections.Counter = collections.Counter()

# (module or class, function name, label): the sub-steps, looked up where their callers find them.
WRAPPED = (
    (st, "track_step", "kcc.track_step"),
    (fe, "orthographic_project", "kcc.ortho"),
    (fe, "depth_translation", "kcc.depth"),
    (co.KernelCorrelator, "channels", "kcc.channels (+keyframes)"),
    (co.KernelCorrelator, "forward", "kcc.predict"),
    (co, "_response_spectrum", "predict.spectrum"),
    (co, "_kernel_map", "spectrum.kernel_map (+keyframes)"),
    (co, "_find_peak", "predict.find_peak"),
    (co, "peak_to_sidelobe", "predict.psr"),
    (co, "shift_variance", "predict.variance"),
    (orm, "_rotate_planar", "ortho.rotate (+resolution)"),
    (st, "backproject", "backproject"),
    (st, "rgbd_to_points", "bp.rgbd_to_points"),
    (st, "sample_grey_warped", "bp.sample_grey_warped"),
    (orm, "grey_from_rgb", "bp.grey_from_rgb"),
    (st, "summarize", "match.summarize"),
    (sy, "fuse_keyframe", "fusion.fuse_keyframe"),
    (sy, "keyframe_filter", "keyframe_filter"),
)


def _wrap(owner, name: str, label: str) -> None:
    fn = getattr(owner, name)

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            TOTAL[label] += time.perf_counter() - t0
            CALLS[label] += 1

    setattr(owner, name, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", default="tum_fr1_xyz", help="a sequence folder under $TORCHSLAM_DATA")
    name = ap.parse_args().sequence
    torch.set_num_threads(1)
    for owner, fn, label in WRAPPED:
        _wrap(owner, fn, label)
    seq = TUMSequence(data_root() / name)
    system = NISlam(config_from_dict(NISlamConfig, {}))
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    t0 = time.perf_counter()
    run_sequence(system, seq)
    wall = time.perf_counter() - t0
    n = len(seq)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / n
    print(f"{name}: {n} frames, {n / wall:.1f} frames/s, load {os.getloadavg()[0]:.2f}, {faults:.0f} minor faults/frame")
    print("stage_ms per frame:", {k: round(v / n, 2) for k, v in system.stage_ms.items()})
    for label in sorted(TOTAL, key=lambda k: -TOTAL[k]):
        print(f"  {label:34s} {1000 * TOTAL[label] / CALLS[label]:7.2f} ms/call  x{CALLS[label]}")


if __name__ == "__main__":
    main()
