"""Benchmark NI-SLAM: accuracy on every sequence per attitude source, frame rates, batched KCC stage.

Writes ``scripts/results/bench_nislam.json`` and ``bench_nislam.png`` and prints markdown tables.

Frame rates per run: ``end-to-end`` is frames over the wall time of ``run_sequence`` (decode on
the prefetching loader's thread, loop closure and the final map included); ``compute`` over the
system's own time; ``front-end`` over the per-frame tracking pipeline alone, the stages
``backproject`` (attitude, back-projection, grey re-sampling), ``kcc`` (``track_step``),
``fusion`` and ``keyframe`` (a new keyframe's map and filter): no decode, no loop closure, no
final map.

    python scripts/bench_nislam.py                 # everything (a few minutes on 2 cores)
    python scripts/bench_nislam.py --quick         # smoke run
    python scripts/bench_nislam.py --settings default,features=learned --out scripts/results/features
                                                   # learned against hand-crafted KCC channels
    python scripts/bench_nislam.py --revisit       # also each real sequence there and back
    python scripts/bench_nislam.py --groups tuning --settings default,pixel_stride=2+kcc.frame_taper=16
                                                   # any setting as dotted keys joined by "+"
    python scripts/bench_nislam.py --revisit --only '*-there-and-back'
                                                   # the there-and-back stand-ins alone

``--windows L`` adds, for every real sequence and stand-in, its windows of ``L`` frames at most
``L / 2`` frames apart (``<name>@<start>``, in the sequence's split): a run's ATE on a 200-300
frame sequence depends on where its few keyframes happen to fall, so a setting compared over
several windows of the same frames is judged on more than one draw of that chance.

``--revisit`` adds, for every real sequence, its there-and-back stand-in
(``scripts/make_revisit.py``: forward, back, forward, back, written to a temporary folder of
links) as the sequence ``<name>-there-and-back`` in the same split: the shipped sequences never
come back to their places, the long ones the issues measure on do.
"""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import json
import os
import tempfile
import time
from pathlib import Path

import torch
import yaml

from _bench import RESULTS, time_calls
from make_revisit import write_revisit
from torchslam.config import config_from_dict
from torchslam.data import Trajectory
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.data.tum import TUMSequence
from torchslam.environment import environment_info
from torchslam.eval import EvaluationError, ate, rpe
from torchslam.kcc import choose_resolution, kcc_features, kcc_train, keyframe_map, orthographic_project, rgbd_to_points
from torchslam.systems import run_sequence
from torchslam.systems.nislam import NISlam, NISlamConfig, attitude_stream, track_step
from torchslam.app.calibrate_time import estimate_attitude_time_offset

PAPER_ATE_M = {"tum_fr1_xyz": 0.011}  # NI-SLAM Table 1 (ground-truth attitude on TUM)


SETTINGS = {
    "default": {},
    # the attitude stream sampled at image stamp + the offset estimated from the images first
    "time-offset": {},
    "pixel_stride=2": {"pixel_stride": 2},
    "pixel_stride=2+ortho240x320": {"pixel_stride": 2, "kcc": {"ortho_height": 240, "ortho_width": 320}},
    # the learned KCC channels (issue 15), packaged weights, every other setting the default's
    "features=learned": {"kcc": {"features": "learned"}},
    # each frame's orthographic image on its own optical axis (the paper) instead of the prediction
    "center=axis": {"center_on_prediction": False},
    # the frame's channels untapered (the default before the frame taper)
    "frame_taper=0": {"kcc": {"frame_taper": 0}},
    # the loop candidates from place recognition alone (no pose-graph proximity candidate)
    "proximity=0": {"loop": {"proximity_candidates": 0}},
    # both of the above: the settings before frames were centred and proximity candidates added
    "center=axis+proximity=0": {"center_on_prediction": False, "loop": {"proximity_candidates": 0}},
}


# Sequences that tuning decisions may look at, and the ones kept out of every tuning decision
# (reported apart). Synthetic sequences cycle through the trajectory kinds by seed.
TUNING_REAL = ("tum_fr1_xyz", "7scenes_redkitchen")
HELD_OUT_REAL = ("hololens_dvmvs",)
TUNING_SEEDS = (0, 1, 2, 3, 4)
HELD_OUT_SEEDS = (100, 101, 102, 103, 104)
SYNTHETIC_KINDS = ("handheld", "translate", "orbit", "loop")
RPE_FRAMES = (1, 10, 30)


@dataclasses.dataclass(frozen=True)
class Window:
    """Frames ``start`` to ``end`` (exclusive) of the real sequence in ``folder`` (``--windows``)."""

    folder: Path
    start: int
    end: int


def window_starts(frames: int, length: int) -> list[int]:
    """Starts of the ``length``-frame windows of a ``frames``-frame sequence: the fewest windows
    at most ``length // 2`` frames apart that reach from its first frame to its last, evenly
    spread (none when the sequence is shorter than a window)."""
    if length < 2:
        raise ValueError(f"--windows: a window needs at least 2 frames, got {length}")
    if frames < length:
        return []
    span = frames - length
    k = -(-span // max(length // 2, 1)) + 1  # ceil(span / step) + 1
    return [round(i * span / (k - 1)) for i in range(k)] if k > 1 else [0]


def setting_values(name: str) -> dict:
    """The config values of a setting: a named one of ``SETTINGS``, or ``key=value`` pairs joined
    by ``+`` with dotted keys of ``NISlamConfig`` (``pixel_stride=2+kcc.ortho_height=300``; values
    read as YAML). Raises ValueError naming the part that is not ``key=value``."""
    if name in SETTINGS:
        return SETTINGS[name]
    values: dict = {}
    for part in name.split("+"):
        key, eq, text = part.partition("=")
        if not eq or not key:
            raise ValueError(f"setting {name!r}: {part!r} is neither a named setting nor key=value")
        *path, leaf = key.split(".")
        node = values
        for k in path:
            node = node.setdefault(k, {})
        node[leaf] = yaml.safe_load(text)
    return values


def _cases(data_root: Path, settings: list[str], quick: bool, revisit: Path | None = None,
           groups: tuple[str, ...] = ("tuning", "held-out"), windows: int | None = None) -> list[tuple[str, str, str, str, object]]:
    """(group, sequence name, attitude, setting, how to load it) for every case whose data exists.

    With ``revisit`` (a folder), each real sequence's there-and-back stand-in is written there
    and added after it, in its split. With ``windows`` (frames), the windows (``window_starts``)
    of each real sequence and stand-in follow them. ``groups`` picks the splits to run.
    """
    cases = []
    for group, names in (("tuning", TUNING_REAL), ("held-out", HELD_OUT_REAL)):
        if group not in groups:
            continue
        for name in names:
            if (data_root / name / "rgb.txt").is_file():
                folders = [(name, data_root / name)]
                if revisit is not None:
                    stand_in = revisit / f"{name}_palindrome"
                    write_revisit(data_root / name, stand_in)
                    folders.append((f"{name}-there-and-back", stand_in))
                if windows is not None:
                    for label, folder in list(folders):
                        n = len(TUMSequence(folder))
                        folders += [(f"{label}@{s}", Window(folder, s, s + windows)) for s in window_starts(n, windows)]
                for label, folder in folders:
                    for att in ("groundtruth", "simulated"):
                        cases += [(group, label, att, st, folder) for st in settings]
    seeds = ((("tuning", TUNING_SEEDS[:1]), ("held-out", HELD_OUT_SEEDS[:1])) if quick
             else (("tuning", TUNING_SEEDS), ("held-out", HELD_OUT_SEEDS)))
    for group, group_seeds in seeds:
        if group not in groups:
            continue
        for seed in group_seeds:
            kind = SYNTHETIC_KINDS[seed % len(SYNTHETIC_KINDS)]
            cases += [(group, f"synthetic-{kind}-{seed}", "imu", st, (kind, seed)) for st in settings if st != "time-offset"]
    return cases


def accuracy(data_root: Path, quick: bool, settings: list[str], revisit: Path | None = None,
             groups: tuple[str, ...] = ("tuning", "held-out"), only: tuple[str, ...] = ("*",),
             windows: int | None = None) -> list[dict]:
    rows = []
    for group, name, att, setting, source in _cases(data_root, settings, quick, revisit, groups, windows):
        if not any(fnmatch.fnmatchcase(name, pattern) for pattern in only):
            continue
        if isinstance(source, tuple):
            kind, seed = source
            seq = generate_sequence(SyntheticConfig(frames=60 if quick else 300, trajectory=kind, seed=seed))
        elif isinstance(source, Window):
            seq = TUMSequence(source.folder, prefetch=2, start=source.start, end=source.end)
        else:
            seq = TUMSequence(source, prefetch=2, end=40 if quick else None)
        values = {"attitude": att, **setting_values(setting)}
        offset = None
        if setting == "time-offset":
            stream = attitude_stream(seq, config_from_dict(NISlamConfig, values))
            offset = estimate_attitude_time_offset(seq, stream, max_pairs=20 if quick else 60).offset
            values["attitude_time_offset"] = offset
        cfg = config_from_dict(NISlamConfig, values)
        t0 = time.perf_counter()
        res = run_sequence(NISlam(cfg), seq)
        wall = time.perf_counter() - t0
        out = res.output
        # The headline ATE of metrics.json: evo's, against the raw ground truth where there is one.
        reference = getattr(seq, "groundtruth_raw", None)
        reference = reference if reference is not None else seq.groundtruth
        est = Trajectory(out.timestamps, out.T_wc)
        a = ate(est, reference)
        rpe_mm = {}
        for delta in RPE_FRAMES:
            try:
                rpe_mm[str(delta)] = 1000 * rpe(est, reference, delta=delta, all_pairs=True).trans_stats["rmse"]
            except EvaluationError:  # too few frames for the step
                rpe_mm[str(delta)] = None
        rows.append({
            "group": group, "sequence": name, "attitude": att, "setting": setting, "attitude_time_offset_s": offset,
            "frames": len(seq), "tracked": len(out.T_wc),
            "keyframes": len(out.keyframe_indices), "loops_accepted": out.metrics["loops"]["accepted"],
            "prior_frames": out.metrics["motion_prior_frames"],
            "ate_rmse_m": a.stats["rmse"], "rpe_rmse_mm": rpe_mm,
            "paper_ate_rmse_m": PAPER_ATE_M.get(name) if att == "groundtruth" else None,
            "fps_end_to_end": res.fps_end_to_end, "fps_compute": res.fps_compute, "wall_s": wall,
            "fps_frontend": _frontend_fps(out.stage_ms, res.frames_processed),
            "stage_ms_per_frame": {k: v / max(res.frames_processed, 1) for k, v in out.stage_ms.items()},
        })
        extra = f" (offset {offset * 1000:+.1f} ms)" if offset is not None else ""
        print(f"  {group:8s} {name:24s} {att:11s} {setting:15s} ATE {a.stats['rmse'] * 100:6.2f} cm  {res.fps_end_to_end:6.1f} fps e2e  "
              f"{res.fps_compute:6.1f} fps compute  {rows[-1]['fps_frontend']:6.1f} fps front-end{extra}", flush=True)
    return rows


FRONTEND_STAGES = ("backproject", "kcc", "fusion", "keyframe")


def _frontend_fps(stage_ms: dict[str, float], frames: int) -> float:
    """Frames/s of the front-end stages alone (see the module docstring)."""
    ms = sum(stage_ms.get(k, 0.0) for k in FRONTEND_STAGES)
    return 1000.0 * frames / ms if ms > 0 else 0.0


def batched_kcc(data_root: Path, sizes: list[int], device: str, repeat: int) -> list[dict]:
    """Frames/s of the per-frame KCC stage (ortho projection + correlation + PSR + depth) vs B."""
    seq = TUMSequence(data_root / "tum_fr1_xyz", end=2)
    f0, f1 = seq[0], seq[1]
    intr = seq.camera.as_tensor(torch.float32, device)[None]
    k = NISlamConfig().kcc
    size = (k.ortho_height, k.ortho_width)
    rows = []
    for B in sizes:
        p0, g0, v0 = rgbd_to_points(f0.rgb[None].to(device), f0.depth[None].to(device), intr)
        p1, g1, v1 = rgbd_to_points(f1.rgb[None].to(device), f1.depth[None].to(device), intr)
        p0, g0, v0 = p0.expand(B, -1, -1).contiguous(), g0.expand(B, -1).contiguous(), v0.expand(B, -1).contiguous()
        p1, g1, v1 = p1.expand(B, -1, -1).contiguous(), g1.expand(B, -1).contiguous(), v1.expand(B, -1).contiguous()
        r = choose_resolution(p0, v0, size, k.coverage, k.sample_step)
        kf = orthographic_project(p0, g0, v0, None, r, size)
        filt = kcc_train(kcc_features(kf.grey, kf.depth, kf.valid, k.channel_norm, k.fill_holes), k.sigma, k.lam)
        km = keyframe_map(kf)
        R = torch.eye(3, device=device).expand(B, 3, 3)
        times = time_calls(lambda: track_step(p1, g1, v1, R, km, filt, r, k), repeat, device).seconds
        best = min(times)
        med = sorted(times)[len(times) // 2]
        rows.append({"device": device, "B": B, "ms_per_batch_median": 1000 * med, "frames_per_s_median": B / med,
                     "frames_per_s_best": B / best})
        print(f"  {device} B={B:3d}: {B / med:8.1f} frames/s (median of {repeat}), {B / best:8.1f} best")
    return rows


def plot(result: dict, path: Path) -> None:
    """ATE per run at the default (horizontal bars, coloured by split, the paper's figure marked) and,
    when it was measured, the batched KCC stage's frames/s against B."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    acc = [r for r in result["accuracy"] if r["setting"] == "default"]
    batched = result["batched_kcc"]
    ncols = 2 if batched else 1
    fig, axes = plt.subplots(1, ncols, figsize=(11 if batched else 7, 0.9 + 0.24 * max(1, len(acc))), squeeze=False)
    ax = axes[0][0]
    colours = {"tuning": "tab:blue", "held-out": "tab:orange"}
    y = list(range(len(acc)))[::-1]
    ax.barh(y, [100 * r["ate_rmse_m"] for r in acc], color=[colours.get(r["group"], "tab:gray") for r in acc])
    for yi, r in zip(y, acc):
        if r["paper_ate_rmse_m"] is not None:
            ax.plot([100 * r["paper_ate_rmse_m"]] * 2, [yi - 0.4, yi + 0.4], "r-", lw=2)
    ax.set_yticks(y, [f"{r['sequence']} · {r['attitude']}" for r in acc], fontsize=7)
    ax.set_xlabel("ATE RMSE (cm)")
    ax.set_title("NI-SLAM at the default settings")
    handles = [matplotlib.patches.Patch(color=c, label=g) for g, c in colours.items() if any(r["group"] == g for r in acc)]
    if any(r["paper_ate_rmse_m"] is not None for r in acc):
        handles.append(matplotlib.lines.Line2D([], [], color="r", lw=2, label="paper"))
    ax.legend(handles=handles, loc="lower right", fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    if batched:
        ax = axes[0][1]
        for dev in sorted({r["device"] for r in batched}):
            rows = [r for r in batched if r["device"] == dev]
            ax.plot([r["B"] for r in rows], [r["frames_per_s_median"] for r in rows], "o-", label=dev)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("batch size B")
        ax.set_ylabel("frames/s (KCC stage)")
        ax.set_title("Batched tracking step")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def paired_table(rows: list[dict], setting: str) -> str:
    """Markdown: each (sequence, attitude) run at ``setting`` beside the default's, with the changes."""
    base = {(r["sequence"], r["attitude"]): r for r in rows if r["setting"] == "default"}
    out = [f"\n{setting} against the default (same sequences, same run of this script):\n",
           "| group | sequence | attitude | ATE default → " + setting + " (cm) | change | RPE 1 / 10 / 30 frames, default → " + setting
           + " (mm) | keyframes | frames/s end-to-end (ratio) | frames/s front-end (ratio) |",
           "|---|---|---|---|---:|---|---|---|---|"]
    for r in rows:
        b = base.get((r["sequence"], r["attitude"]))
        if r["setting"] != setting or b is None:
            continue
        rpe = lambda x: " / ".join("–" if v is None else f"{v:.1f}" for v in x["rpe_rmse_mm"].values())
        change = 100 * (r["ate_rmse_m"] / b["ate_rmse_m"] - 1)
        out.append(
            f"| {r['group']} | {r['sequence']} | {r['attitude']} | {100 * b['ate_rmse_m']:.2f} → {100 * r['ate_rmse_m']:.2f} | "
            f"{change:+.0f} % | {rpe(b)} → {rpe(r)} | {b['keyframes']} → {r['keyframes']} | "
            f"{b['fps_end_to_end']:.1f} → {r['fps_end_to_end']:.1f} ({r['fps_end_to_end'] / b['fps_end_to_end']:.2f}) | "
            f"{b['fps_frontend']:.1f} → {r['fps_frontend']:.1f} ({r['fps_frontend'] / b['fps_frontend']:.2f}) |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.environ.get("TORCHSLAM_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data")))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--settings", default=",".join(SETTINGS),
                    help=f"comma-separated: any of {', '.join(SETTINGS)}, or dotted key=value pairs joined by '+'")
    ap.add_argument("--groups", default="tuning,held-out", help="comma-separated splits to run: tuning, held-out")
    ap.add_argument("--only", default="*",
                    help="comma-separated patterns of the sequences to run (fnmatch: '*-there-and-back', 'synthetic-*')")
    ap.add_argument("--no-batched", action="store_true", help="skip the batched KCC stage timings")
    ap.add_argument("--windows", type=int, default=None, metavar="L",
                    help="also run each real sequence's windows of L frames, at most L/2 frames apart (<name>@<start>)")
    ap.add_argument("--revisit", action="store_true",
                    help="also run each real sequence there and back (scripts/make_revisit.py, in a temporary folder)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    root = Path(args.data)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"machine": environment_info(), "quick": args.quick}
    print(f"machine: {result['machine']}")
    print("accuracy and frame rate per sequence:")
    settings = args.settings.split(",")
    for x in settings:
        try:
            config_from_dict(NISlamConfig, setting_values(x))
        except (ValueError, TypeError, KeyError) as e:
            ap.error(f"--settings: {x!r}: {e} (named settings: {', '.join(SETTINGS)})")
    if args.windows is not None and args.windows < 2:
        ap.error(f"--windows: a window needs at least 2 frames, got {args.windows}")
    groups = tuple(args.groups.split(","))
    if not groups or any(g not in ("tuning", "held-out") for g in groups):
        ap.error(f"--groups: expected tuning and/or held-out, got {args.groups!r}")
    result["groups"] = list(groups)
    with tempfile.TemporaryDirectory(prefix="torchslam-revisit-") as tmp:
        result["accuracy"] = accuracy(root, args.quick, settings, Path(tmp) if args.revisit else None, groups,
                                      tuple(args.only.split(",")), args.windows)
    result["revisit"] = args.revisit
    result["windows"] = args.windows
    sizes = [1, 4] if args.quick else [1, 2, 4, 8, 16, 32, 64]
    result["batched_kcc"] = []
    if not args.no_batched:
        print("batched KCC stage:")
        result["batched_kcc"] = batched_kcc(root, sizes, "cpu", 3 if args.quick else 5)
        if torch.cuda.is_available():
            result["batched_kcc"] += batched_kcc(root, sizes, "cuda", 20)
    (out / "bench_nislam.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result, out / "bench_nislam.png")
    print("\n| group | sequence | attitude | setting | frames | keyframes | loops | ATE RMSE (cm) | paper (cm) | RPE 1 / 10 / 30 frames (mm) | frames/s end-to-end | frames/s compute | frames/s front-end |")
    print("|---|---|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|")
    for r in result["accuracy"]:
        paper = f"{100 * r['paper_ate_rmse_m']:.1f}" if r["paper_ate_rmse_m"] else "–"
        off = r["attitude_time_offset_s"]
        setting = r["setting"] if off is None else f"time offset {1000 * off:+.1f} ms"
        rpe_text = " / ".join("–" if v is None else f"{v:.1f}" for v in r["rpe_rmse_mm"].values())
        print(f"| {r['group']} | {r['sequence']} | {r['attitude']} | {setting} | {r['frames']} | {r['keyframes']} | {r['loops_accepted']} | "
              f"{100 * r['ate_rmse_m']:.2f} | {paper} | {rpe_text} | {r['fps_end_to_end']:.1f} | {r['fps_compute']:.1f} | {r['fps_frontend']:.1f} |")
    for group in ("tuning", "held-out"):
        rows = [r for r in result["accuracy"] if r["group"] == group]
        for setting in settings:
            vals = [100 * r["ate_rmse_m"] for r in rows if r["setting"] == setting]
            if vals:
                print(f"mean ATE, {group}, {setting}: {sum(vals) / len(vals):.2f} cm over {len(vals)} runs")
    for setting in settings:
        if setting != "default" and "default" in settings:
            print(paired_table(result["accuracy"], setting))
    if result["batched_kcc"]:
        print("\n| device | B | frames/s (median) | frames/s (best) |\n|---|---:|---:|---:|")
    for r in result["batched_kcc"]:
        print(f"| {r['device']} | {r['B']} | {r['frames_per_s_median']:.1f} | {r['frames_per_s_best']:.1f} |")


if __name__ == "__main__":
    main()
