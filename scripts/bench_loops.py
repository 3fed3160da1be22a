"""Benchmark NI-SLAM's loop acceptance: long revisiting sequences with planted true and false loops.

Three parts, each printed as a markdown table and written to ``scripts/results/bench_loops.json``:

* ``nees``: the normalised estimation error of the odometry edges against ground truth (loops
  off), per axis group, with the loop test's covariances ("configured": the frames' jitter under
  the default ``loop.acceptance_covariance``) and with the matches' raw Eq. (19) ones (scales 1,
  no floor): the calibration of ``loop.jitter_variance_scale``, ``loop.translation_variance_scale``,
  ``loop.depth_variance_scale`` and the rotation model.
  Tuning seeds 0-4 and held-out seeds 100-104 are reported apart.
* ``long``: long synthetic sequences along the "loop" trajectory, which revisit their start
  once near the end (with and without depth noise), per attitude source: loops verified,
  accepted and rejected, and the ATE with and without loop closure. At every verified loop two
  planted false loops are tested first and undone (``PlantedNISlam``): the verified transform
  moved by each of ``--false-offsets`` metres, and the verified transform attached to a
  keyframe half the sequence away (a different place); each should be rejected. The same runs with the old
  acceptance rule (``max_odometry_bend_m`` 0.05 m, no chi-square test) are the baseline.
* ``window``: ``loop.local_window`` on and off (ATE and frame time), when asked for.

    python scripts/bench_loops.py                # everything (long: tens of minutes on 2 cores)
    python scripts/bench_loops.py --quick        # smoke run (short sequences)
    python scripts/bench_loops.py --only nees    # one part
    python scripts/bench_loops.py --merge a.json b.json   # parts run apart, into bench_loops.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import torch

from _bench import RESULTS
from torchslam.config import config_from_dict
from torchslam.data import Trajectory
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.eval import ate
from torchslam.geometry import se3_from_Rt, se3_inverse, se3_log, so3_log
from torchslam.systems import run_sequence
from torchslam.systems.nislam import NISlam, NISlamConfig

TUNING_SEEDS = (0, 1, 2, 3, 4)
HELD_OUT_SEEDS = (100, 101, 102, 103, 104)
# The acceptance rule before the chi-square test: the optimised graph may bend no odometry
# edge's translation by more than 5 cm (the chi-square test made permissive).
OLD_RULE = {"max_odometry_bend_m": 0.05, "chi2_quantile": 1 - 1e-15}
RULES = {"chi2": {}, "old-bend": OLD_RULE, "no-loops": {"enabled": False}}


class PlantedNISlam(NISlam):
    """NI-SLAM that tests planted false loops before every verified one, then undoes them.

    The planted loops: the verified transform moved by each of ``false_offsets`` metres (along
    x + y), and the verified transform attached to the keyframe halfway between the two (a
    different place). Whatever the test decides, the system's graph, poses and counters are
    restored before the verified loop is tried, so the true loops are measured as without them.

    Attributes:
        false_offsets: metres added to the verified loop's translation.
        planted: per planted loop, its kind, the chi-square increase and whether it was accepted.
    """

    def __init__(self, cfg: NISlamConfig, false_offsets: tuple[float, ...]):
        super().__init__(cfg)
        self.false_offsets = false_offsets
        self.planted: list[dict] = []

    def _try_loop(self, j_old, k_new, T_jk, variance, window=None, rotation_cov=None):
        if window is None and len(self.keyframes) > 2:
            direction = torch.tensor([1.0, 1.0, 0.0], dtype=T_jk.dtype) / math.sqrt(2)
            trials = []
            for offset in self.false_offsets:
                shifted = T_jk.clone()
                shifted[:3, 3] += offset * direction
                trials.append((f"offset {offset:g} m", j_old, shifted))
            mid = (j_old + k_new) // 2
            if abs(mid - j_old) > 2:
                trials.append(("elsewhere", mid, T_jk))
            for kind, j, T in trials:
                saved = ([list(x) for x in (self.edges_i, self.edges_j, self.edges_T, self.edges_info, self.edges_test_info, self.edges_loop)],
                         [kf.T_wk for kf in self.keyframes], self.R_corr, self._history_start, dict(self.loops))
                accepted = super()._try_loop(j, k_new, T, variance, rotation_cov=rotation_cov)
                test = self.loop_tests.pop()
                self.planted.append({"kind": kind, "accepted": accepted, "chi2_increase": test["chi2_increase"]})
                lists, poses, self.R_corr, self._history_start, self.loops = saved
                self.edges_i, self.edges_j, self.edges_T, self.edges_info, self.edges_test_info, self.edges_loop = lists
                for kf, T_wk in zip(self.keyframes, poses):
                    kf.T_wk = T_wk
        return super()._try_loop(j_old, k_new, T_jk, variance, window, rotation_cov)


def odometry_errors(system: NISlam, groundtruth: Trajectory) -> dict[str, torch.Tensor]:
    """Per odometry edge: its translation error in node i's axes and variance, rotation error and variance.

    Returns:
        dict with ``e_t`` (E, 3) m, ``var_t`` (E, 3) m^2, ``e_r`` (E, 3) rad, ``var_r`` (E, 3) rad^2,
        of the edges whose keyframes have ground truth.
    """
    # The keyframes' poses belong to their depth instants (``Frame.geometry_time``).
    stamps = getattr(system, "keyframe_times", None) or [kf.timestamp for kf in system.keyframes]
    times = torch.tensor(stamps, dtype=torch.float64)
    T_gt, ok = groundtruth.interpolate(times)
    odo = [e for e, loop in enumerate(system.edges_loop) if not loop]
    if not odo:
        empty = torch.zeros(0, 3, dtype=torch.float64)
        return {"e_t": empty, "var_t": empty, "e_r": empty, "var_r": empty}
    i = torch.tensor([system.edges_i[e] for e in odo], dtype=torch.int64)
    j = torch.tensor([system.edges_j[e] for e in odo], dtype=torch.int64)
    keep = ok[i] & ok[j]
    i, j = i[keep], j[keep]
    T_meas = torch.stack([system.edges_T[e] for e in odo])[keep]
    info = torch.stack([system.edges_test_info[e] for e in odo])[keep]  # the loop test's covariances
    T_true = se3_inverse(T_gt[i]) @ T_gt[j]
    r = se3_log(se3_inverse(T_meas) @ T_true)  # (E, 6), translation in node j's axes
    R = T_meas[:, :3, :3]
    e_t = (R @ r[:, :3, None])[..., 0]  # in node i's axes, where the match measured it
    info_t = R @ info[:, :3, :3] @ R.transpose(-1, -2)
    var_t = 1.0 / torch.diagonal(info_t, dim1=-2, dim2=-1)
    var_r = 1.0 / torch.diagonal(info[:, 3:, 3:], dim1=-2, dim2=-1)
    return {"e_t": e_t, "var_t": var_t, "e_r": r[:, 3:], "var_r": var_r}


def _nees_stats(errs: list[dict[str, torch.Tensor]]) -> dict[str, float]:
    e_t = torch.cat([e["e_t"] for e in errs])
    var_t = torch.cat([e["var_t"] for e in errs])
    e_r = torch.cat([e["e_r"] for e in errs])
    var_r = torch.cat([e["var_r"] for e in errs])
    n_t = e_t**2 / var_t
    n_r = e_r**2 / var_r
    return {
        "edges": int(e_t.shape[0]),
        # mean NEES per degree of freedom (1 when the covariances are honest)
        "nees_xy": float(n_t[:, :2].mean()), "nees_z": float(n_t[:, 2].mean()), "nees_rot": float(n_r.mean()),
        "nees_xy_median": float(n_t[:, :2].median()), "nees_z_median": float(n_t[:, 2].median()),
        "rms_error_xy_mm": 1000 * float(e_t[:, :2].pow(2).mean().sqrt()), "rms_error_z_mm": 1000 * float(e_t[:, 2].pow(2).mean().sqrt()),
        "rms_error_rot_deg": math.degrees(float(e_r.pow(2).mean().sqrt())),
        "rms_sigma_xy_mm": 1000 * float(var_t[:, :2].mean().sqrt()), "rms_sigma_z_mm": 1000 * float(var_t[:, 2].mean().sqrt()),
    }


class _Miscalibrated:
    """A sequence whose camera reports focal lengths ``scale`` times those it was rendered with."""

    def __init__(self, seq, scale: float):
        self._seq = seq
        cam = seq.camera
        self.camera = dataclasses.replace(cam, fx=cam.fx * scale, fy=cam.fy * scale)

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def __iter__(self):
        return iter(self._seq)

    def __len__(self) -> int:
        return len(self._seq)


class OracleRotationNISlam(PlantedNISlam):
    """An experiment, not a capability: every verified loop takes the ground truth's relative
    rotation, trusted to ``sigma_deg`` per axis, where NI-SLAM's loop edge carries the attitude
    stream's rotation and no rotation information. What a visual rotation at loops could give at best.
    """

    def __init__(self, cfg: NISlamConfig, false_offsets: tuple[float, ...], groundtruth: Trajectory, sigma_deg: float):
        super().__init__(cfg, false_offsets)
        self.groundtruth = groundtruth
        self.sigma_deg = sigma_deg
        self.rotation_errors_deg: list[float] = []

    def _verify(self, cand, kf, centred=False):
        edge = super()._verify(cand, kf, centred)
        if edge is None:
            return None
        R_gt = self.groundtruth.T_wc[[self.keyframes[cand].frame_index, kf.frame_index], :3, :3].to(torch.float64)
        R = R_gt[0].T @ R_gt[1]
        self.rotation_errors_deg.append(math.degrees(float(so3_log(edge.T_jk[:3, :3].T @ R).norm())))
        return dataclasses.replace(edge, T_jk=se3_from_Rt(R, edge.T_jk[:3, 3]))

    def _information(self, T_ij, variance, dt, depth, loop, scaled=True, extra=0.0):
        info = super()._information(T_ij, variance, dt, depth, loop, scaled, extra)
        if loop:
            info[3:, 3:] = torch.eye(3, dtype=torch.float64) / math.radians(self.sigma_deg) ** 2
        return info


def _synthetic(seed: int, frames: int, noise: bool, period: float, trajectory: str = "loop"):
    return generate_sequence(SyntheticConfig(
        frames=frames, period=period, trajectory=trajectory, seed=seed, width=320, height=240, depth_noise=noise,
    ))


class _RecordingNISlam(NISlam):
    """NI-SLAM that keeps each odometry edge's Eq. (19) match variance (for the NEES)."""

    def __init__(self, cfg: NISlamConfig):
        super().__init__(cfg)
        self.raw: list[torch.Tensor] = []
        self.keyframe_times: list[float] = []

    def _new_keyframe(self, src, previous=None):
        self.keyframe_times.append(src.input.frame.geometry_time)
        if previous is not None:
            self.raw.append(src.variance)
        super()._new_keyframe(src, previous)


def _with_raw(errs: dict[str, torch.Tensor], raw: list) -> dict:
    """``errs`` with the matches' Eq. (19) variances instead of the configured ones (no scale, no floor)."""
    if not raw:
        return errs
    return {**errs, "var_t": torch.stack([v.to(torch.float64) for v in raw])}


def nees(
    quick: bool, frames: int, overrides: dict, dump: str | None = None,
    splits: tuple[str, ...] = ("tuning", "held-out"), kinds: tuple[str, ...] = ("loop", "handheld", "orbit"),
    attitudes: tuple[str, ...] = ("groundtruth", "simulated"),
) -> list[dict]:
    """NEES of odometry edges on synthetic sequences, per attitude source, tuning and held-out seeds."""
    frames = 60 if quick else frames
    rows = []
    from _bench import data_root
    from torchslam.data.tum import TUMSequence

    root = data_root()
    for split, names, seeds in (("tuning", ("tum_fr1_xyz", "7scenes_redkitchen"), TUNING_SEEDS),
                                ("held-out", ("hololens_dvmvs",), HELD_OUT_SEEDS)):
        if split not in splits:
            continue
        seeds = seeds[:1] if quick else seeds
        sources = [(f"synthetic-{kind}-{seed}", seed, kind) for seed in seeds for kind in kinds]
        sources += [(name, None, None) for name in names if (root / name / "rgb.txt").is_file()]
        for att in attitudes:
            per = {"configured": [], "raw": []}
            by_sequence = {}
            for name, seed, kind in sources:
                if seed is None:
                    seq = TUMSequence(root / name, prefetch=2, end=40 if quick else None)
                    gt = seq.groundtruth_raw if seq.groundtruth_raw is not None else seq.groundtruth
                else:
                    seq = _synthetic(seed, frames, True, 10.0, kind)
                    gt = seq.groundtruth
                cfg = config_from_dict(NISlamConfig, {"attitude": att, "loop": {**overrides, "enabled": False}})
                system = _RecordingNISlam(cfg)
                run_sequence(system, seq)
                errs = odometry_errors(system, gt)
                if len(system.raw) != len(errs["e_t"]):
                    raise RuntimeError(f"{name}: an odometry edge without ground truth: the NEES needs every keyframe's")
                per["configured"].append(errs)  # the system's own edge covariances
                per["raw"].append(_with_raw(errs, list(system.raw)))
                by_sequence[name] = per["configured"][-1]
            if not quick:
                for name, errs in by_sequence.items():
                    if not name.startswith("synthetic") and len(errs["e_t"]):
                        stats = _nees_stats([errs])
                        rows.append({"split": split, "attitude": att, "covariance": f"configured, {name}", "frames": None, **stats})
            for name, errs in per.items():
                stats = _nees_stats(errs)
                rows.append({"split": split, "attitude": att, "covariance": name, "frames": frames, **stats})
                print(f"  nees {split:8s} {att:11s} {name:10s} xy {stats['nees_xy']:7.3f} z {stats['nees_z']:7.3f} "
                      f"rot {stats['nees_rot']:7.2f} ({stats['edges']} edges)", flush=True)
            if dump:
                torch.save({"per": per, "names": [n for n, _, _ in sources]}, f"{dump}_{split}_{att}.pt")
    return rows


def long_runs(
    quick: bool, false_offsets: tuple[float, ...], attitudes: list[str], rules: list[str], noises: tuple[bool, ...] = (False, True),
    overrides: dict | None = None, seed: int = 0, frames: int | None = None, focal_scale: float = 1.0,
    oracle_rotation_deg: float | None = None, sim_seed: int = 0,
) -> list[dict]:
    """Long loop sequences: loops and ATE with the chi-square test and with the old bend rule.

    ``overrides``: loop settings applied under every rule's own (``--loop``); ``seed``: the
    synthetic sequence's (``--long-seed``; 0 is a tuning seed, 100-104 are held out); ``frames``:
    its length (``--long-frames``; the same lap in fewer frames moves faster); ``focal_scale``:
    the focal lengths the system is given, as a multiple of the rendering's (``--long-focal-scale``;
    1.03 makes a systematic odometry drift, as a miscalibrated camera does); ``oracle_rotation_deg``:
    run ``OracleRotationNISlam`` with that sigma (``--oracle-loop-rotation``; an experiment);
    ``sim_seed``: the simulated IMU's noise draw (``--sim-seed``).
    """
    frames = frames or (150 if quick else 1500)
    # One lap that takes 90 % of the sequence: the last tenth revisits the start.
    period = frames / 30.0 * 0.9
    rows = []
    for noise in noises:
        seq = _synthetic(seed, frames, noise, period)
        if focal_scale != 1.0:
            seq = _Miscalibrated(seq, focal_scale)
        for att in attitudes:
            for rule, loop in RULES.items():
                if rule not in rules:
                    continue
                cfg = config_from_dict(NISlamConfig, {"attitude": att, "sim_seed": sim_seed, "loop": {**(overrides or {}), **loop}})
                if oracle_rotation_deg is None:
                    system = PlantedNISlam(cfg, false_offsets)
                else:
                    system = OracleRotationNISlam(cfg, false_offsets, seq.groundtruth, oracle_rotation_deg)
                t0 = time.perf_counter()
                res = run_sequence(system, seq)
                wall = time.perf_counter() - t0
                out = res.output
                a = ate(Trajectory(out.timestamps, out.T_wc), seq.groundtruth)
                loops = out.metrics["loops"]
                planted = system.planted
                row = {
                    "frames": frames, "seed": seed, "focal_scale": focal_scale, "depth_noise": noise, "attitude": att, "rule": rule,
                    "keyframes": len(out.keyframe_indices), "ate_rmse_m": a.stats["rmse"], **{f"loops_{k}": v for k, v in loops.items()},
                    "planted_false": len(planted), "planted_false_accepted": sum(p["accepted"] for p in planted),
                    "planted_accepted_by_kind": {k: sum(p["accepted"] for p in planted if p["kind"] == k) for k in sorted({p["kind"] for p in planted})},
                    "loop_tests": out.metrics["loop_tests"], "planted": planted,
                    "sim_seed": sim_seed, "loop_visual_rotation": out.metrics.get("loop_visual_rotation"),
                    "loop_edge_rotation_errors_deg": _loop_edge_rotation_errors(system, seq.groundtruth),
                    "wall_s": wall,
                }
                if oracle_rotation_deg is not None:
                    row["oracle_loop_rotation_deg"] = oracle_rotation_deg
                    row["loop_attitude_errors_deg"] = system.rotation_errors_deg
                rows.append(row)
                print(f"  long noise={noise!s:5s} {att:11s} {rule:8s} ATE {100 * a.stats['rmse']:6.2f} cm  verified "
                      f"{loops['verified']} accepted {loops['accepted']} chi2-rejected {loops['rejected_by_chi2']} "
                      f"bend-rejected {loops['rejected_by_odometry']}  planted false accepted "
                      f"{row['planted_false_accepted']}/{row['planted_false']} {row['planted_accepted_by_kind']}  loop edge rotation errors "
                      f"{[round(e, 3) for e in row['loop_edge_rotation_errors_deg']]} deg", flush=True)
    return rows


def _loop_edge_rotation_errors(system: NISlam, groundtruth: Trajectory) -> list[float]:
    """Per accepted loop edge, the angle between its rotation and the ground truth's relative rotation, degrees."""
    times = torch.tensor([kf.timestamp for kf in system.keyframes], dtype=torch.float64)
    T_gt, ok = groundtruth.interpolate(times)
    out = []
    for i, j, T, loop in zip(system.edges_i, system.edges_j, system.edges_T, system.edges_loop):
        if loop and bool(ok[i]) and bool(ok[j]):
            R_true = T_gt[i, :3, :3].T @ T_gt[j, :3, :3]
            out.append(math.degrees(float(so3_log(T[:3, :3].T @ R_true).norm())))
    return out


def window(quick: bool, size: int) -> list[dict]:
    """ATE and time per frame with ``loop.local_window`` off and ``size``, A/B interleaved per sequence.

    Tuning: tum_fr1_xyz, 7scenes_redkitchen (ground-truth and simulated attitude) and synthetic
    seeds 0-4; held out: hololens_dvmvs and seeds 100-104 (hand-held pans, 200 frames).
    """
    from _bench import data_root
    from torchslam.data.tum import TUMSequence

    root = data_root()
    cases = []
    for split, names, seeds in (("tuning", ("tum_fr1_xyz", "7scenes_redkitchen"), TUNING_SEEDS),
                                ("held-out", ("hololens_dvmvs",), HELD_OUT_SEEDS)):
        for name in names:
            if (root / name / "rgb.txt").is_file():
                for att in ("groundtruth", "simulated"):
                    cases.append((split, name, att, None))
        for seed in seeds[:1] if quick else seeds:
            cases.append((split, f"synthetic-handheld-{seed}", "imu", seed))
    rows = []
    for split, name, att, seed in cases:
        if seed is None:
            seq = TUMSequence(root / name, prefetch=2, end=30 if quick else None)
        else:
            seq = _synthetic(seed, 40 if quick else 200, True, 10.0, "handheld")
        row = {"split": split, "sequence": name, "attitude": att}
        for w in (0, size):
            system = NISlam(config_from_dict(NISlamConfig, {"attitude": att, "loop": {"local_window": w}}))
            res = run_sequence(system, seq)
            out = res.output
            reference = getattr(seq, "groundtruth_raw", None) or seq.groundtruth
            a = ate(Trajectory(out.timestamps, out.T_wc), reference)
            row[f"ate_m_w{w}"] = a.stats["rmse"]
            row[f"ms_per_frame_w{w}"] = 1000 / res.fps_compute
            row[f"local_w{w}"] = out.metrics["local_window"]
        rows.append(row)
        print(f"  window {split:8s} {name:24s} {att:11s} ATE {100 * row['ate_m_w0']:6.2f} -> {100 * row[f'ate_m_w{size}']:6.2f} cm  "
              f"time x{row[f'ms_per_frame_w{size}'] / row['ms_per_frame_w0']:.3f}  local edges {row[f'local_w{size}']}", flush=True)
    return rows


def markdown(result: dict) -> str:
    lines = []
    if result.get("nees"):
        lines += ["| split | attitude | covariance | edges | NEES x,y | NEES z | NEES rot | RMS err x,y (mm) | RMS σ x,y (mm) | RMS err z (mm) | RMS σ z (mm) | RMS err rot (°) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in result["nees"]:
            lines.append(f"| {r['split']} | {r['attitude']} | {r['covariance']} | {r['edges']} | {r['nees_xy']:.2f} | {r['nees_z']:.3f} | "
                         f"{r['nees_rot']:.2f} | {r['rms_error_xy_mm']:.2f} | {r['rms_sigma_xy_mm']:.2f} | {r['rms_error_z_mm']:.2f} | "
                         f"{r['rms_sigma_z_mm']:.2f} | {r['rms_error_rot_deg']:.3f} |")
        lines.append("")
    if result.get("long"):
        lines += ["| seed | frames | depth noise | attitude | rule | ATE (cm) | verified | accepted | rejected χ² | rejected bend | planted false accepted |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in result["long"]:
            lines.append(f"| {r.get('seed', 0)} | {r['frames']} | {r['depth_noise']} | {r['attitude']} | {r['rule']} | {100 * r['ate_rmse_m']:.2f} | "
                         f"{r['loops_verified']} | {r['loops_accepted']} | {r['loops_rejected_by_chi2']} | "
                         f"{r['loops_rejected_by_odometry']} | {r['planted_false_accepted']}/{r['planted_false']} "
                         f"({', '.join(f'{k}: {v}' for k, v in r['planted_accepted_by_kind'].items())}) |")
        lines.append("")
    if result.get("window"):
        size = result["window_size"]
        lines += [f"| split | sequence | attitude | ATE window 0 (cm) | ATE window {size} (cm) | local edges accepted/verified | time ratio |",
                  "|---|---|---|---|---|---|---|"]
        for r in result["window"]:
            loc = r[f"local_w{size}"]
            lines.append(f"| {r['split']} | {r['sequence']} | {r['attitude']} | {100 * r['ate_m_w0']:.2f} | {100 * r[f'ate_m_w{size}']:.2f} | "
                         f"{loc['accepted']}/{loc['verified']} | {r[f'ms_per_frame_w{size}'] / r['ms_per_frame_w0']:.3f} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short sequences (smoke run)")
    ap.add_argument("--only", choices=["nees", "long", "window"], default=None, help="run one part")
    ap.add_argument("--window", type=int, default=3, help="loop.local_window compared with 0 (part window)")
    ap.add_argument("--false-offsets", default="0.3,1.0", help="metres added to planted false loops' translations (comma-separated)")
    ap.add_argument("--attitudes", default="groundtruth,simulated", help="attitude sources of the long runs (comma-separated)")
    ap.add_argument("--nees-frames", type=int, default=200, help="frames of each NEES sequence")
    ap.add_argument("--loop", default="{}", help="JSON overrides of the loop section (e.g. a calibration to check)")
    ap.add_argument("--nees-splits", default="tuning,held-out", help="NEES: tuning, held-out or both")
    ap.add_argument("--nees-kinds", default="loop,handheld,orbit", help="NEES: synthetic trajectories")
    ap.add_argument("--nees-attitudes", default="groundtruth,simulated", help="NEES: attitude sources")
    ap.add_argument("--dump-nees", default=None, help="save the per-edge errors and variances under this path prefix (torch.save)")
    ap.add_argument("--rules", default="chi2,old-bend,no-loops", help="acceptance rules of the long runs (comma-separated)")
    ap.add_argument("--depth-noise", default="off,on", help="depth noise of the long runs: off, on or both (comma-separated)")
    ap.add_argument("--long-seed", type=int, default=0, help="seed of the long runs' synthetic sequence (100-104: held out)")
    ap.add_argument("--long-frames", type=int, default=None, help="frames of the long runs' lap (default 1500; fewer: faster motion)")
    ap.add_argument("--long-focal-scale", type=float, default=1.0, help="focal lengths given to the system / rendered ones (1.03: systematic drift)")
    ap.add_argument("--oracle-loop-rotation", type=float, default=None, metavar="SIGMA_DEG",
                    help="experiment: verified loops take the ground truth's relative rotation at this sigma (long runs)")
    ap.add_argument("--sim-seed", type=int, default=0, help="the simulated IMU's noise draw (long runs)")
    ap.add_argument("--out", default=str(RESULTS / "bench_loops.json"), help="JSON output")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="combine the parts of earlier runs (each a JSON this script wrote) into --out and print their tables")
    args = ap.parse_args()
    if args.merge:
        result: dict = {}
        for path in args.merge:
            with open(path) as f:
                part = json.load(f)
            for key, value in part.items():
                result[key] = result.get(key, []) + value if isinstance(value, list) else value
        print(markdown(result))
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        return
    torch.set_num_threads(int(__import__("os").environ.get("OMP_NUM_THREADS", "1")))
    result: dict = {"quick": args.quick}
    if args.only in (None, "nees"):
        result["nees"] = nees(args.quick, args.nees_frames, json.loads(args.loop), args.dump_nees,
                              tuple(args.nees_splits.split(",")), tuple(args.nees_kinds.split(",")), tuple(args.nees_attitudes.split(",")))
    if args.only in (None, "long"):
        result["long"] = long_runs(args.quick, tuple(float(x) for x in args.false_offsets.split(",")), args.attitudes.split(","), args.rules.split(","),
                                   tuple({"off": False, "on": True}[x] for x in args.depth_noise.split(",")), json.loads(args.loop), args.long_seed, args.long_frames, args.long_focal_scale,
                                   args.oracle_loop_rotation, args.sim_seed)
    if args.only in (None, "window"):
        result["window_size"] = args.window
        result["window"] = window(args.quick, args.window)
    print(markdown(result))
    if not args.quick or args.out != str(RESULTS / "bench_loops.json"):
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
