"""GC-SLAM's accuracy under settings side by side, on every kind of sequence at hand.

Each case runs ``torchslam run --system gcslam`` in a fresh process per front-end and setting and
reads its ``metrics.json``: the shipped sequences, their there-and-back stand-ins for long
revisiting sequences (``scripts/make_revisit.py``), every n-th frame of them (faster motion,
``data.stride``; ``--strides`` sets them for every real sequence) and synthetic sequences. Each case carries its split: ``tuning`` (fr1/xyz,
7-Scenes, synthetic seeds 0-4) or ``held-out`` (HoloLens, synthetic seeds 100-104), so that a
default chosen on the first can be judged on the second.

    python scripts/bench_gcslam_settings.py --settings spread_corrections=false,spread_corrections=true \
        --out scripts/results/spread_corrections/bench_gcslam_settings

A setting is ``default`` or dotted ``key=value`` pairs joined by ``+``. Writes ``OUT.json`` and
``OUT.md`` (ATE RMSE in cm per case, front-end and setting; the last setting against the first).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench import REPO_ROOT, RESULTS, data_root

from torchslam.environment import environment_info

REAL = [("tum_fr1_xyz", "tuning"), ("7scenes_redkitchen", "tuning"), ("hololens_dvmvs", "held-out")]
STRIDES = {"tum_fr1_xyz": (4, 6), "7scenes_redkitchen": (4, 8), "hololens_dvmvs": (2, 3)}
SYNTHETIC = [(0, "handheld"), (1, "translate"), (2, "orbit"), (3, "loop"), (4, "handheld"),
             (100, "handheld"), (101, "translate"), (102, "orbit"), (103, "loop"), (104, "handheld")]


def cases(root: Path, revisit_root: Path | None, groups: set[str], strides: tuple[int, ...] | None = None) -> list[dict]:
    """Every case: its name, split, the folder (or ``synthetic``) and its extra ``--set`` pairs
    (``strides``: every real sequence's, else each one's own ``STRIDES``)."""
    out = []
    for name, split in REAL:
        if not (root / name / "rgb.txt").is_file():
            print(f"skipped {name}: not found under {root}", file=sys.stderr)
            continue
        out.append(dict(name=name, split=split, data=str(root / name), sets=[], kind="shipped"))
        if revisit_root is not None:
            out.append(dict(name=f"{name}-there-and-back", split=split, data=str(revisit_root / f"{name}_palindrome"), sets=[],
                            kind="there-and-back"))
        for s in strides or STRIDES[name]:
            out.append(dict(name=f"{name}/{s}", split=split, data=str(root / name), sets=[f"data.stride={s}"], kind="stride"))
    for seed, trajectory in SYNTHETIC:
        split = "tuning" if seed < 100 else "held-out"
        out.append(dict(name=f"synthetic-{trajectory}-{seed}", split=split, data="synthetic", kind="synthetic",
                        sets=[f"data.synthetic.seed={seed}", f"data.synthetic.trajectory={trajectory}", "data.synthetic.frames=300"]))
    return [c for c in out if c["kind"] in groups]


def run_case(case: dict, frontend: str, setting: str, workdir: Path, threads: int) -> dict:
    sets = list(case["sets"]) + [f"frontend={frontend}"]
    if setting != "default":
        sets += setting.split("+")
    out = workdir / "run"
    cmd = [sys.executable, "-m", "torchslam", "run", "--system", "gcslam", "--data", case["data"], "--out", str(out),
           "--overwrite", "--no-tensorboard", "--no-progress", "--threads", str(threads)]
    for s in sets:
        cmd += ["--set", s]
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        return dict(error=done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}")
    m = json.loads((out / "metrics.json").read_text())
    return dict(ate_cm=None if m.get("ate_rmse_m") is None else 100 * m["ate_rmse_m"],
                rpe_mm=None if m.get("rpe_trans_rmse_m") is None else 1000 * m["rpe_trans_rmse_m"], rpe_delta=m.get("rpe_delta"),
                keyframes=m["keyframes"],
                loops=m["loops"]["accepted"], fps=m["fps_end_to_end"], tracking_failures=m["tracking"]["tracking_failures"])


def table(rows: list[dict], settings: list[str], frontends: list[str]) -> str:
    first, last = settings[0], settings[-1]
    head = "| split | case | " + " | ".join(f"{fe}: {first} → {last}" for fe in frontends) + " |"
    lines = [head, "|---|---|" + "---|" * len(frontends)]
    for r in rows:
        cells = []
        for fe in frontends:
            a, b = r["runs"][fe][first], r["runs"][fe][last]
            if a.get("ate_cm") is None or b.get("ate_cm") is None:
                cells.append(f"{a.get('error', '–')} → {b.get('error', '–')}")
                continue
            cells.append(f"{a['ate_cm']:.3f} → {b['ate_cm']:.3f} ({100 * (b['ate_cm'] / a['ate_cm'] - 1):+.1f} %)")
        lines.append(f"| {r['split']} | {r['name']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--settings", default="default", help="comma-separated: default, or dotted key=value pairs joined by '+'")
    ap.add_argument("--frontends", default="sparse,dense")
    ap.add_argument("--groups", default="shipped,there-and-back,stride,synthetic")
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--strides", default="", help="comma-separated strides for every real sequence (default: each one's own)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_gcslam_settings")
    args = ap.parse_args()
    try:
        strides = tuple(int(s) for s in args.strides.split(",") if s) or None
    except ValueError:
        ap.error(f"--strides {args.strides}: expected comma-separated whole numbers, e.g. 2,4")
    if strides and min(strides) < 1:
        ap.error(f"--strides {args.strides}: expected strides of at least 1")
    settings = args.settings.split(",")
    frontends = args.frontends.split(",")
    groups = set(args.groups.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        revisit = None
        if "there-and-back" in groups:
            names = [n for n, _ in REAL if (args.data / n / "rgb.txt").is_file()]
            subprocess.run([sys.executable, str(REPO_ROOT / "scripts" / "make_revisit.py"), "--data", str(args.data),
                            "--out", str(tmp / "revisit"), *names], check=True, capture_output=True)
            revisit = tmp / "revisit"
        rows = []
        for case in cases(args.data, revisit, groups, strides):
            row = dict(name=case["name"], split=case["split"], kind=case["kind"], runs={})
            for fe in frontends:
                row["runs"][fe] = {}
                for setting in settings:
                    res = run_case(case, fe, setting, tmp, args.threads)
                    row["runs"][fe][setting] = res
                    print(f"{case['split']:8s} {case['name']:40s} {fe:6s} {setting:32s} "
                          + (f"ATE {res['ate_cm']:.3f} cm, RPE {res['rpe_mm'] or float('nan'):.2f} mm, {res['keyframes']} keyframes, {res['loops']} loops"
                             if res.get("ate_cm") is not None else res.get("error", "no ATE")), flush=True)
            rows.append(row)
    md = table(rows, settings, frontends)
    print(md)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(
        dict(machine=environment_info(), threads=args.threads, settings=settings, frontends=frontends, rows=rows), indent=1))
    args.out.with_suffix(".md").write_text(md + "\n")


if __name__ == "__main__":
    main()
