"""The README's Results tables, from one folder of benchmark results (and, with --run, those results).

    python scripts/results_tables.py scripts/results/defaults_2026-12-07          # print the tables
    python scripts/results_tables.py DIR --run                                    # run every benchmark into DIR first

The folder holds what these commands write (``--run`` runs them, one after the other, one thread;
about an hour on the 2-core development machine):

    bench_nislam.py --settings default --no-batched --threads 1 --revisit        -> bench_nislam.json, .png
    bench_gcslam_settings.py --settings default --frontends sparse,dense          -> bench_gcslam.json, .md
    eval_sequences.py --with-nislam                                               -> eval_sequences.json, .md
    bench_loops.py --only long --rules chi2 --long-seed S  (S = 0, 100)           -> bench_loops_long_seed{S}.json
    bench_checkouts.py --other <this checkout> --rounds 3 [--busy 1]              -> bench_checkouts_{idle,busy}.json
    bench_cpu.py --system S [--set ...]  (three runs, CPU_RUNS)                   -> bench_cpu_{nislam,gcslam_sparse,gcslam_dense}.json

``bench_checkouts`` compares this checkout with itself: two alternating runs of the same code, so
their spread is the machine's noise. The tables printed are the README's: NI-SLAM per sequence and
attitude, the long loops, GC-SLAM's accuracy, its per-stage times, the frame rates idle and
busy and the CPU per frame thread by thread (``tests/scripts/test_results_tables.py`` checks that the README shows the stored folder's).
A table whose file is missing is left out, saying so.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

NAMES = {"tum_fr1_xyz": "fr1/xyz", "7scenes_redkitchen": "7-Scenes", "hololens_dvmvs": "HoloLens"}
SPLITS = {"tuning": "tuning", "held-out": "held out"}
SYSTEMS = {"nislam": "NI-SLAM", "gcslam-sparse": "GC-SLAM sparse", "gcslam-dense": "GC-SLAM dense"}
STAGES = [  # (column, stage_ms key) of GC-SLAM's per-stage table
    ("ORB", "orb_extraction"), ("dense preparation", "dense_preparation"), ("registration", "registration"),
    ("keyframe insertion", "keyframe_insertion"), ("pair refinement", "optimizer/pair_refinement"),
    ("loop detection", "optimizer/loop_detection"), ("loop registration", "optimizer/loop_registration"),
    ("FastGO", "optimizer/fastgo"),
]
# The CPU table's rows (``bench_cpu.py``): result file, the run's name, its ``--set`` values, and
# what its frame-preparing thread or process does.
CPU_RUNS = [
    ("bench_cpu_nislam.json", "NI-SLAM, simulated attitude", ["--system", "nislam", "--set", "attitude=simulated"],
     "attitude, back-projection"),
    ("bench_cpu_gcslam_sparse.json", "GC-SLAM sparse", ["--system", "gcslam"], "ORB, in a child process"),
    ("bench_cpu_gcslam_dense.json", "GC-SLAM dense", ["--system", "gcslam", "--set", "frontend=dense"],
     "pyramids, in a child process"),
]
# bench_cpu.py's thread names, grouped into the CPU table's columns.
CPU_GROUPS = {"tracking": ("main (tracking)",), "preparing": ("tslam-prepare", "tslam-ahead"), "decoding": ("tslam-decode",),
              "optimisation": ("tslam-optimizer",)}


def display(name: str) -> str:
    """A sequence's name as the tables show it: ``tum_fr1_xyz-there-and-back`` -> ``fr1/xyz there and back``."""
    base, _, stride = name.partition("/")
    back = base.endswith("-there-and-back")
    base = base.removesuffix("-there-and-back")
    out = NAMES.get(base, base) + (" there and back" if back else "")
    return f"{out} /{stride}" if stride else out


def _synthetic_seed(name: str) -> str | None:
    """The seed of ``synthetic-KIND-SEED``, else None."""
    parts = name.split("-")
    return parts[-1] if parts[0] == "synthetic" and len(parts) == 3 else None


def _split_order(rows: list[dict], split_key: str, name_key: str) -> list[dict]:
    """Tuning before held out; within each, real sequences before synthetic ones (stable)."""
    order = {"tuning": 0, "held-out": 1}
    return sorted(rows, key=lambda r: (order.get(r[split_key], 2), _synthetic_seed(r[name_key]) is not None))


def nislam_table(result: dict) -> str:
    """NI-SLAM per sequence and attitude at the default (``bench_nislam.json``), synthetic seeds one row per split."""
    rows = _split_order([r for r in result["accuracy"] if r["setting"] == "default"], "group", "sequence")
    out = ["| split | sequence | attitude | frames | keyframes | loops | ATE (cm) | RPE 1 / 10 / 30 frames (mm) | frames/s end to end / front-end |",
           "|---|---|---|---:|---:|---:|---:|---|---|"]
    for group in dict.fromkeys(r["group"] for r in rows):  # in order: tuning, then held out
        members = [r for r in rows if r["group"] == group]
        for r in members:
            if _synthetic_seed(r["sequence"]) is not None:
                continue
            ate = f"{100 * r['ate_rmse_m']:.2f}"
            if r.get("paper_ate_rmse_m"):
                ate = f"**{ate}** (paper {100 * r['paper_ate_rmse_m']:.1f})"
            rpe = " / ".join("–" if v is None else f"{v:.1f}" for v in r["rpe_rmse_mm"].values())
            out.append(f"| {SPLITS[group]} | {display(r['sequence'])} | {r['attitude']} | {r['frames']} | {r['keyframes']} | "
                       f"{r['loops_accepted']} | {ate} | {rpe} | {r['fps_end_to_end']:.1f} / {r['fps_frontend']:.1f} |")
        syn = [r for r in members if _synthetic_seed(r["sequence"]) is not None]
        if syn:  # the split's synthetic seeds in one row, after its real sequences
            seeds = " / ".join(_synthetic_seed(r["sequence"]) for r in syn)
            frames = {r["frames"] for r in syn}
            frames_text = f"{frames.pop()} each" if len(frames) == 1 else " / ".join(str(r["frames"]) for r in syn)
            ates = " / ".join(f"{100 * r['ate_rmse_m']:.2f}" for r in syn)
            attitudes = " / ".join(sorted({r["attitude"] for r in syn}))
            out.append(f"| {SPLITS[group]} | synthetic {seeds} | {attitudes} | {frames_text} | | | {ates} | | |")
    means = []
    for group in ("tuning", "held-out"):
        vals = [100 * r["ate_rmse_m"] for r in rows if r["group"] == group]
        if vals:
            means.append(f"{SPLITS[group]} {sum(vals) / len(vals):.2f} cm over {len(vals)} runs")
    return "\n".join(out) + "\n\nMean ATE: " + ", ".join(means) + "."


def loops_table(results: list[dict]) -> str:
    """The long loops with planted false ones (``bench_loops_long_seed*.json``), one row per seed and depth noise."""
    runs = [r for res in results for r in res["long"] if r["rule"] == "chi2"]
    out = ["| seed | depth noise | ATE, ground-truth attitude (cm) | ATE, simulated attitude (cm) | true loops kept | "
           "false loops accepted, of 2 each: elsewhere / 1 m off / 0.3 m off |",
           "|---|---|---:|---:|---|---|"]
    keys = sorted({(r["seed"], r["depth_noise"]) for r in runs})
    for seed, noise in keys:
        by_att = {r["attitude"]: r for r in runs if r["seed"] == seed and r["depth_noise"] == noise}
        ate = {a: f"{100 * by_att[a]['ate_rmse_m']:.2f}" if a in by_att else "–" for a in ("groundtruth", "simulated")}
        kept = {f"{r['loops_accepted']} / {r['loops_verified']}" for r in by_att.values()}
        false = {" / ".join(str(r["planted_accepted_by_kind"].get(k, "–")) for k in ("elsewhere", "offset 1 m", "offset 0.3 m"))
                 for r in by_att.values()}
        split = "tuning" if seed < 100 else "held out"
        out.append(f"| {seed} ({split}) | {'on' if noise else 'off'} | {ate['groundtruth']} | {ate['simulated']} | "
                   f"{'; '.join(sorted(kept))} | {'; '.join(sorted(false))} |")
    return "\n".join(out)


def gcslam_table(result: dict) -> str:
    """GC-SLAM's ATE per sequence and front-end at the default (``bench_gcslam.json``); strides and synthetic seeds grouped."""
    setting = result["settings"][0]
    rows = _split_order(result["rows"], "split", "name")
    fronts = result["frontends"]
    groups: list[tuple[str, str, list[dict]]] = []  # (split, label, rows)
    for r in rows:
        seed = _synthetic_seed(r["name"])
        base, _, stride = r["name"].partition("/")
        if seed is not None:
            key = (r["split"], "synthetic")
        elif stride:
            key = (r["split"], base + "/")
        else:
            key = (r["split"], r["name"])
        if groups and (groups[-1][0], groups[-1][1]) == key:
            groups[-1][2].append(r)
        else:
            groups.append((key[0], key[1], [r]))
    out = ["| split | sequence | " + " | ".join(fronts) + " |", "|---|---|" + "---:|" * len(fronts)]
    for split, key, members in groups:
        if key == "synthetic":
            label, sep = "synthetic " + " / ".join(_synthetic_seed(m["name"]) for m in members), " / "
        elif key.endswith("/"):
            label, sep = display(key[:-1]) + " " + ", ".join("/" + m["name"].partition("/")[2] for m in members), ", "
        else:
            label, sep = display(key), ", "
        cells = [sep.join(f"{m['runs'][f][setting]['ate_cm']:.2f}" for m in members) for f in fronts]
        out.append(f"| {SPLITS[split]} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def stage_table(result: dict) -> str:
    """GC-SLAM's ms per frame of each stage and its frame rate (``eval_sequences.json``)."""
    rows = [r for r in result["rows"] if r["system"] == "gcslam"]
    order = list(NAMES)
    rows.sort(key=lambda r: (order.index(r["sequence"]) if r["sequence"] in order else len(order), r["sequence"],
                             ["sparse", "dense"].index(r["frontend"]) if r["frontend"] in ("sparse", "dense") else 2))
    out = ["| sequence | front-end | frames/s end to end | " + " | ".join(c for c, _ in STAGES) + " |",
           "|---|---|---:|" + "---:|" * len(STAGES)]
    for r in rows:
        cells = ["–" if r["stage_ms"].get(k) is None else f"{r['stage_ms'][k]:.1f}" for _, k in STAGES]
        out.append(f"| {display(r['sequence'])} | {r['frontend']} | {r['fps_end_to_end']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def speed_table(idle: dict, busy: dict) -> str:
    """Frames/s idle and busy of two checkouts of the same code (``bench_checkouts_{idle,busy}.json``)."""
    b = {(r["system"], r["sequence"]): r for r in busy["rows"]}

    def cell(row: dict) -> str:
        v = [x for runs in row["fps"].values() for x in runs]
        return f"{statistics.median(v):.1f} ({min(v):.1f}–{max(v):.1f})"

    out = ["| system | sequence | idle: median (range) | beside one busy process: median (range) | "
           "the two identical checkouts' ratio, idle / busy |", "|---|---|---|---|---|"]
    for r in idle["rows"]:
        k = (r["system"], r["sequence"])
        busy_cell, busy_ratio = (cell(b[k]), f"{b[k]['ratio']:.2f}") if k in b else ("–", "–")
        out.append(f"| {SYSTEMS.get(r['system'], r['system'])} | {display(r['sequence'])} | {cell(r)} | {busy_cell} | "
                   f"{r['ratio']:.2f} / {busy_ratio} |")
    return "\n".join(out)


def cpu_table(runs: list[tuple[str, str, dict]]) -> str:
    """CPU ms per frame thread by thread (``bench_cpu_*.json``): ``(name, what prepares, result)`` per row.

    Columns group ``bench_cpu.py``'s thread names (``CPU_GROUPS``); "all" is the median over rounds
    of every thread's sum, helpers included, so the columns need not add up to it."""
    out = ["| run | tracking (main thread) | preparing frames | decoding | optimisation process | all | wall time per frame |",
           "|---|---:|---:|---:|---:|---:|---:|"]
    for name, prepares, r in runs:
        med = r["median_ms_per_frame"]

        def group(key: str) -> float | None:
            found = [med[n] for n in CPU_GROUPS[key] if n in med]
            return sum(found) if found else None

        prep, opt = group("preparing"), group("optimisation")
        cells = [f"{group('tracking') or 0.0:.1f}", "–" if prep is None else f"{prep:.1f} ({prepares})",
                 f"{group('decoding') or 0.0:.1f}", "–" if opt is None else f"{opt:.1f}",
                 f"{r['total_ms_per_frame']:.1f}", f"{r['median_wall_ms_per_frame']:.1f}"]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def tables(folder: Path) -> dict[str, str]:
    """Every table the files in ``folder`` give, by name; a missing file leaves its table out."""
    def load(name: str) -> dict | None:
        p = folder / name
        return json.loads(p.read_text()) if p.exists() else None

    out: dict[str, str] = {}
    if (r := load("bench_nislam.json")) is not None:
        out["nislam"] = nislam_table(r)
    loops = [json.loads(p.read_text()) for p in sorted(folder.glob("bench_loops_long_seed*.json"))]
    if loops:
        out["loops"] = loops_table(loops)
    if (r := load("bench_gcslam.json")) is not None:
        out["gcslam"] = gcslam_table(r)
    if (r := load("eval_sequences.json")) is not None:
        out["stages"] = stage_table(r)
    idle, busy = load("bench_checkouts_idle.json"), load("bench_checkouts_busy.json")
    if idle is not None and busy is not None:
        out["speed"] = speed_table(idle, busy)
    cpu = [(name, prepares, r) for file, name, _, prepares in CPU_RUNS if (r := load(file)) is not None]
    if cpu:
        out["cpu"] = cpu_table(cpu)
    return out


def run_all(folder: Path) -> None:
    """Run every benchmark the tables need, writing into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    py, root = sys.executable, HERE.parent
    commands = [
        [py, HERE / "bench_nislam.py", "--settings", "default", "--no-batched", "--threads", "1", "--revisit", "--out", folder],
        [py, HERE / "bench_gcslam_settings.py", "--settings", "default", "--frontends", "sparse,dense", "--threads", "1",
         "--out", folder / "bench_gcslam"],
        [py, HERE / "eval_sequences.py", "--with-nislam", "--runs", folder / "runs", "--out", folder / "eval_sequences"],
        *[[py, HERE / "bench_loops.py", "--only", "long", "--rules", "chi2", "--long-seed", str(s),
           "--out", folder / f"bench_loops_long_seed{s}.json"] for s in (0, 100)],
        [py, HERE / "bench_checkouts.py", "--other", root, "--systems", "nislam,gcslam-sparse,gcslam-dense",
         "--sequences", "tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs", "--rounds", "3", "--out", folder / "bench_checkouts_idle.json"],
        [py, HERE / "bench_checkouts.py", "--other", root, "--systems", "nislam,gcslam-sparse,gcslam-dense",
         "--sequences", "tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs", "--rounds", "3", "--busy", "1",
         "--out", folder / "bench_checkouts_busy.json"],
        *[[py, HERE / "bench_cpu.py", *args, "--out", folder / file] for file, _, args, _ in CPU_RUNS],
    ]
    for cmd in commands:
        print("running:", " ".join(str(c) for c in cmd[1:]), flush=True)
        subprocess.run([str(c) for c in cmd], check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("folder", type=Path, help="the folder of benchmark results")
    ap.add_argument("--run", action="store_true", help="run every benchmark into the folder first (about an hour)")
    args = ap.parse_args()
    if args.run:
        run_all(args.folder)
    elif not args.folder.is_dir():
        ap.error(f"{args.folder}: no such folder (use --run to create it)")
    found = tables(args.folder)
    for name in ("nislam", "loops", "gcslam", "stages", "speed", "cpu"):
        print(f"\n<!-- {name} -->\n{found[name]}" if name in found else f"\n<!-- {name}: no result file in {args.folder} -->")


if __name__ == "__main__":
    main()
