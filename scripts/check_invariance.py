"""Record every system's trajectories on a fixed set of cases, or compare two recordings.

A change that must not alter behaviour (a restructuring, a clean-up) records before and after:

    python scripts/check_invariance.py record scripts/out/before.pt
    ... change ...
    python scripts/check_invariance.py record scripts/out/after.pt
    python scripts/check_invariance.py compare scripts/out/before.pt scripts/out/after.pt

The cases: NI-SLAM with each attitude source the sequence offers and GC-SLAM with each front-end,
on the three shared real sequences (``$TORCHSLAM_DATA``, default ``../shared/data``) and on the
four synthetic trajectory kinds. Everything runs on one thread with GC-SLAM's optimisation inline,
so a recording is deterministic. ``compare`` prints the largest position difference per case
and exits 1 when any exceeds ``--tol`` metres (default 1e-9) or a case is missing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
REAL = ("tum_fr1_xyz", "7scenes_redkitchen", "hololens_dvmvs")
SYNTHETIC_KINDS = ("orbit", "translate", "loop", "handheld")
SYNTHETIC = ["data.synthetic.frames=90", "data.synthetic.width=320", "data.synthetic.height=240"]


def _cases(data_root: Path) -> list[tuple[str, str, str, list[str]]]:
    """(case name, system, data, --set overrides) for every case whose data exists."""
    cases = []
    sources = [(name, str(data_root / name), []) for name in REAL if (data_root / name / "rgb.txt").is_file()]
    sources += [(f"synthetic-{k}", "synthetic", [*SYNTHETIC, f"data.synthetic.trajectory={k}"]) for k in SYNTHETIC_KINDS]
    for name, data, sets in sources:
        attitudes = ("imu", "simulated", "groundtruth") if data == "synthetic" else ("simulated", "groundtruth")
        for att in attitudes:
            cases.append((f"{name}/nislam-{att}", "nislam", data, [*sets, f"attitude={att}"]))
        for frontend in ("sparse", "dense"):
            cases.append((f"{name}/gcslam-{frontend}", "gcslam", data, [*sets, f"frontend={frontend}", "threaded=false"]))
    return cases


def _run_case(system: str, data: str, overrides: list[str]) -> dict[str, torch.Tensor]:
    from torchslam.systems import get_system, run_sequence
    from torchslam.app.run import load_sequence, resolve_config

    spec = get_system(system)
    cfg, data_cfg, _ = resolve_config(system, None, overrides)
    sequence = load_sequence(data, data_cfg)
    result = run_sequence(spec.build(cfg, device="cpu"), sequence)
    out = result.output
    return {
        "frame_indices": out.frame_indices.clone(),
        "T_wc": out.T_wc.to(torch.float64).clone(),
        "keyframe_indices": out.keyframe_indices.clone(),
        "keyframe_T_wc": out.keyframe_T_wc.to(torch.float64).clone(),
    }


def record(path: Path, data_root: Path, only: str | None) -> None:
    torch.set_num_threads(1)
    cases = [c for c in _cases(data_root) if only is None or only in c[0]]
    recording: dict[str, dict[str, torch.Tensor]] = {}
    for name, system, data, overrides in cases:
        t0 = time.perf_counter()
        recording[name] = _run_case(system, data, overrides)
        n = len(recording[name]["frame_indices"])
        print(f"{name}: {n} poses, {len(recording[name]['keyframe_indices'])} keyframes, {time.perf_counter() - t0:.1f} s", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(recording, path)
    print(f"recorded {len(recording)} cases: {path}")


def _position_diff(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float | str:
    for key in ("frame_indices", "keyframe_indices"):
        if not torch.equal(a[key], b[key]):
            return f"{key} differ ({len(a[key])} vs {len(b[key])})"
    diff = 0.0
    for key in ("T_wc", "keyframe_T_wc"):
        if len(a[key]):
            diff = max(diff, float((a[key][:, :3, 3] - b[key][:, :3, 3]).norm(dim=-1).max()))
    return diff


def compare(before: Path, after: Path, tol: float) -> int:
    a, b = torch.load(before, weights_only=True), torch.load(after, weights_only=True)
    bad = 0
    width = max(len(k) for k in a | b)
    for name in sorted(a | b):
        if name not in a or name not in b:
            print(f"{name:<{width}}  missing in {'before' if name not in a else 'after'}")
            bad += 1
            continue
        d = _position_diff(a[name], b[name])
        ok = not isinstance(d, str) and d <= tol
        bad += not ok
        shown = d if isinstance(d, str) else f"max position difference {d:.3g} m"
        print(f"{name:<{width}}  {shown}{'' if ok else '  <-- differs'}")
    print(f"{len(a | b) - bad}/{len(a | b)} cases agree to {tol:g} m")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("record", help="run every case and save the trajectories")
    p.add_argument("path", type=Path)
    p.add_argument("--only", default=None, help="only the cases whose name contains this text")
    c = sub.add_parser("compare", help="compare two recordings")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    c.add_argument("--tol", type=float, default=1e-9, help="largest position difference accepted, metres (default 1e-9)")
    args = parser.parse_args(argv)
    if args.command == "record":
        root = Path(os.environ.get("TORCHSLAM_DATA", REPO.parent / "shared" / "data"))
        record(args.path, root, args.only)
        return 0
    return compare(args.before, args.after, args.tol)


if __name__ == "__main__":
    sys.exit(main())
