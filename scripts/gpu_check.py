"""The accelerator check: one command that says whether torchslam's GPU path is right and how fast it is.

    python scripts/gpu_check.py                       # on the GPU (about 5 minutes on one H200)
    python scripts/gpu_check.py --device cpu --quick  # the same checks, small, on the CPU (CI runs this)

Three parts, each recorded whatever the others do (a part that raises is reported with its error
and the rest still run):

1. ``pytest -m cuda``: the CUDA tests (on a machine without CUDA they skip; ``--device cpu`` does
   not run them).
2. Agreement of the device with the CPU, each against a tolerance:
   - NI-SLAM and GC-SLAM (dense front-end) trajectories on two synthetic sequences and on frames
     of a shared sequence (``$TORCHSLAM_DATA``, when present): largest position difference,
     1e-4 m;
   - FastGO and the SE(3) pose graph on a repeated-route graph in float64: largest pose entry
     difference, 1e-8;
   - lockstep NI-SLAM on the device, B sequences in one batch against each alone on the device:
     1e-5 m.
3. Timings on the device (frames in device memory, the clock read after synchronising):
   - NI-SLAM front-end (projection, KCC predict, PSR, depth translation, fusion) over B
     sequences, frames/s in aggregate;
   - whole lockstep NI-SLAM over B sequences, frames/s in aggregate;
   - GC-SLAM dense registration of B frame pairs, pairs/s;
   - FastGO to convergence and the pose graph on N keyframes, milliseconds.

Full size: B = 64, 640 x 480 synthetic frames, N = 5,000. ``--quick``: B = 4, 160 x 120, N = 300.
Writes ``gpu_check.json`` and ``gpu_check.md`` (the table) to ``--out`` (default
``scripts/results``) and prints the table; exits 1 when an agreement check fails or a part
raises.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import subprocess
import sys
import time
import traceback
from pathlib import Path

import torch

from _bench import data_root, load_average, sync

REPO = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class Size:
    B: int
    height: int
    width: int
    frames: int
    keyframes: int
    repeat: int


FULL = Size(B=64, height=480, width=640, frames=30, keyframes=5000, repeat=5)
QUICK = Size(B=4, height=120, width=160, frames=8, keyframes=300, repeat=2)


def _nislam_cfg(size: Size, features: str = "handcrafted", **extra):
    from torchslam.config import config_from_dict
    from torchslam.systems.nislam import NISlamConfig

    kcc = {} if size is FULL else {"ortho_height": 90, "ortho_width": 120}
    kcc["features"] = features
    return config_from_dict(NISlamConfig, {"attitude": "imu", "kcc": kcc, **extra})


def _synthetic(size: Size, seed: int, kind: str = "orbit"):
    from torchslam.data.synthetic import SyntheticConfig, generate_sequence

    return generate_sequence(SyntheticConfig(frames=size.frames, trajectory=kind, seed=seed, height=size.height, width=size.width))


class _InMemory:
    """A sequence's frames held on ``device`` (playing it costs no decoding or copying)."""

    def __init__(self, source, device: str, name: str | None = None):
        self.name = name or source.name
        self.camera = source.camera
        self.groundtruth = source.groundtruth
        self.attitude = getattr(source, "attitude", None)
        self.timestamps = source.timestamps
        self.frames = [dataclasses.replace(f, rgb=f.rgb.to(device), depth=f.depth.to(device)) for f in source]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int):
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)


def _max_position_diff(a, b) -> float:
    return float((a.T_wc[:, :3, 3].cpu() - b.T_wc[:, :3, 3].cpu()).abs().max())


def _run_system(system_cfg, seq, device: str):
    from torchslam.systems import run_sequence
    from torchslam.systems.registry import spec_for_config

    return run_sequence(spec_for_config(system_cfg).build(system_cfg, device=device), seq).output


# --------------------------------------------------------------------------------------------- parts


def part_pytest(device: str) -> dict:
    if device == "cpu":
        return {"status": "not run (--device cpu)"}
    cmd = [sys.executable, "-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", str(REPO / "tests")]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    tail = (done.stdout + done.stderr).strip().splitlines()[-1:] or [""]
    return {"status": "passed" if done.returncode == 0 else f"failed (exit {done.returncode})", "summary": tail[0]}


def part_agreement(device: str, size: Size) -> list[dict]:
    from torchslam.config import config_from_dict
    from torchslam.systems.gcslam import GCSlamConfig

    rows = []
    sequences = [_synthetic(size, 0, "orbit"), _synthetic(size, 1, "handheld")]
    real = data_root() / "tum_fr1_xyz"
    if (real / "rgb.txt").is_file():
        from torchslam.data.tum import TUMSequence

        sequences.append(TUMSequence(real, end=size.frames * 3))
    systems = {
        "nislam": lambda seq: _nislam_cfg(size, attitude="imu" if seq.groundtruth is None or "synthetic" in seq.name else "groundtruth"),
        "nislam-learned-channels": lambda seq: _nislam_cfg(
            size, features="learned", attitude="imu" if seq.groundtruth is None or "synthetic" in seq.name else "groundtruth"),
        "gcslam-dense": lambda seq: config_from_dict(GCSlamConfig, {"frontend": "dense"}),
    }
    for seq in sequences:
        for name, cfg_of in systems.items():
            cfg = cfg_of(seq)
            cpu = _run_system(cfg, seq, "cpu")
            dev = _run_system(cfg, seq, device)
            d = _max_position_diff(cpu, dev)
            rows.append({"check": f"{name} on {seq.name}", "difference": d, "tolerance": 1e-4, "unit": "m", "ok": d <= 1e-4})
    rows += _backend_agreement(device, size)
    rows.append(_lockstep_agreement(device, size))
    return rows


def _graphs(N: int):
    from torchslam.fastgo.synthetic import loop_route_problem
    from torchslam.geometry import se3_inverse

    P = loop_route_problem(N, loops_per_keyframe=3, local_pairs=2, correspondences=16, noise=0.01,
                           drift_rot=1e-3, drift_trans=2e-3, seed=0)
    i, j = P.pairs[:, 0], P.pairs[:, 1]
    T_ij = se3_inverse(P.T_gt[i]) @ P.T_gt[j]
    info = torch.eye(6, dtype=torch.float64).expand(len(i), 6, 6).clone() * 1e4
    return P, (P.T_init, i, j, T_ij, info)


def _backend_agreement(device: str, size: Size) -> list[dict]:
    from torchslam.backend import optimize_pose_graph
    from torchslam.fastgo import optimize

    P, graph = _graphs(size.keyframes)
    a = optimize(P.T_init, P.pairs, P.stats).T_wc
    b = optimize(P.T_init.to(device), P.pairs.to(device), P.stats.to(device)).T_wc.cpu()
    c = optimize_pose_graph(*graph).T_wc
    d = optimize_pose_graph(*(t.to(device) for t in graph)).T_wc.cpu()
    out = []
    for name, x, y in (("FastGO", a, b), ("pose graph", c, d)):
        diff = float((x - y).abs().max())
        out.append({"check": f"{name}, N = {size.keyframes}, float64", "difference": diff, "tolerance": 1e-8, "unit": "", "ok": diff <= 1e-8})
    return out


def _lockstep_agreement(device: str, size: Size) -> dict:
    from torchslam.systems.lockstep import run_lockstep

    cfg = _nislam_cfg(size)
    B = min(size.B, 8)
    seqs = [_InMemory(_synthetic(size, 10 + b), device, f"synthetic-{b}") for b in range(B)]
    together = run_lockstep(cfg, seqs, device=device, max_batch=B)
    alone = [_run_system(cfg, s, device) for s in seqs]
    for r in together:
        if isinstance(r, BaseException):
            raise r
    d = max(_max_position_diff(r.output, a) for r, a in zip(together, alone))
    return {"check": f"lockstep NI-SLAM, B = {B} batched vs alone", "difference": d, "tolerance": 1e-5, "unit": "m", "ok": d <= 1e-5}


def _timed(fn, device: str, repeat: int) -> float:
    """Best wall time of ``repeat`` calls after one warm-up, seconds."""
    fn()
    sync(device)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        sync(device)
        best = min(best, time.perf_counter() - t0)
    return best


def part_timings(device: str, size: Size) -> list[dict]:
    rows = [_time_frontend(device, size), _time_lockstep(device, size), _time_dense(device, size)]
    rows += _time_backend(device, size)
    return rows


def _time_frontend(device: str, size: Size) -> dict:
    from torchslam.kcc import fuse_keyframe, track_step
    from torchslam.systems.batching import stack_dataclass, stack_rows
    from torchslam.systems.nislam import NISlam
    from torchslam.systems.nislam.step import backproject

    cfg = _nislam_cfg(size)
    pool = [_synthetic(size, 200 + k) for k in range(min(size.B, 8))]
    systems, inputs = [], []
    for b in range(size.B):
        src = pool[b % len(pool)]
        s = NISlam(cfg, device=device)
        s.start(src)
        s.track(src[0])
        systems.append(s)
        inputs.append(s.prepare(src[1]))
    clouds = backproject(inputs)
    kfs = [s.keyframes[-1] for s in systems]
    args = (
        stack_rows([c.points for c in clouds]), stack_rows([c.grey for c in clouds]), stack_rows([c.valid for c in clouds]),
        torch.stack([(k.T_wk[:3, :3].T @ w.R_att[0]) for k, w in zip(kfs, inputs)]).to(device, torch.float32),
        stack_dataclass([k.map for k in kfs]), stack_dataclass([k.filter for k in kfs]),
        torch.cat([k.resolution for k in kfs]), systems[0].correlator,
    )
    kf_map = args[4]

    def step():
        res = track_step(*args)
        fuse_keyframe(kf_map, res.frame, res.index, res.t_content[:, 2], res.matched, res.psr, cfg.kcc.T_M)

    t = _timed(step, device, size.repeat)
    return {"timing": f"NI-SLAM front-end, B = {size.B}", "value": size.B / t, "unit": "frames/s (aggregate)"}



def _time_lockstep(device: str, size: Size) -> dict:
    from torchslam.systems.lockstep import run_lockstep

    cfg = _nislam_cfg(size, loop={"enabled": False})
    seqs = [_InMemory(_synthetic(size, 300 + b % 8), device, f"synthetic-{b}") for b in range(min(size.B, 8))]
    seqs = [seqs[b % len(seqs)] for b in range(size.B)]
    frames = size.B * size.frames

    def run():
        for r in run_lockstep(cfg, seqs, device=device, max_batch=size.B):
            if isinstance(r, BaseException):
                raise r

    t = _timed(run, device, 1)
    return {"timing": f"lockstep NI-SLAM, B = {size.B}, {size.frames} frames each", "value": frames / t, "unit": "frames/s (aggregate)"}


def _time_dense(device: str, size: Size) -> dict:
    from torchslam.registration.dense import register_dense

    seq = _synthetic(size, 400)
    f0, f1 = seq[0], seq[1]

    def rows(x):
        return x.to(device)[None].expand(size.B, *x.shape).contiguous()

    a = (rows(f0.rgb), rows(f0.depth), rows(f1.rgb), rows(f1.depth))
    t = _timed(lambda: register_dense(*a, seq.camera), device, size.repeat)
    return {"timing": f"GC-SLAM dense registration, B = {size.B} pairs", "value": size.B / t, "unit": "pairs/s"}


def _time_backend(device: str, size: Size) -> list[dict]:
    from torchslam.backend import optimize_pose_graph
    from torchslam.fastgo import optimize

    P, graph = _graphs(size.keyframes)
    T0, pairs, stats = P.T_init.to(device), P.pairs.to(device), P.stats.to(device)
    g = tuple(t.to(device) for t in graph)
    from torchslam.fastgo import FastGOConfig

    t_fastgo = _timed(lambda: optimize(T0, pairs, stats), device, size.repeat)
    # The level schedule batches one elimination-tree level per call; nested dissection makes the
    # tree shallow (band order's is a chain): the fewest launches, the accelerator's candidate.
    level = FastGOConfig(ordering="nested", schedule="level")
    t_level = _timed(lambda: optimize(T0, pairs, stats, config=level), device, size.repeat)
    t_graph = _timed(lambda: optimize_pose_graph(*g), device, size.repeat)
    n = f"N = {size.keyframes}, {len(P.pairs)} pairs"
    return [
        {"timing": f"FastGO to convergence, {n}", "value": 1e3 * t_fastgo, "unit": "ms"},
        {"timing": f"FastGO to convergence, {n}, nested order, level schedule", "value": 1e3 * t_level, "unit": "ms"},
        {"timing": f"pose graph, N = {size.keyframes}, {len(P.pairs)} edges", "value": 1e3 * t_graph, "unit": "ms"},
    ]


# --------------------------------------------------------------------------------------------- report


def _machine(device: str) -> dict:
    info = {"python": platform.python_version(), "torch": torch.__version__, "device": device,
            "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(), "load": load_average()}
    if device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def table(result: dict) -> str:
    lines = [f"Machine: {result['machine']}", "", "| agreement check | difference | tolerance | ok |", "|---|---:|---:|---|"]
    for r in result.get("agreement", []):
        lines.append(f"| {r['check']} | {r['difference']:.2e} {r['unit']} | {r['tolerance']:.0e} | {'yes' if r['ok'] else 'NO'} |")
    lines += ["", "| timing | value | unit |", "|---|---:|---|"]
    for r in result.get("timings", []):
        lines.append(f"| {r['timing']} | {r['value']:.1f} | {r['unit']} |")
    lines += ["", f"pytest -m cuda: {result['pytest'].get('status')} {result['pytest'].get('summary', '')}".rstrip()]
    for part, err in result.get("errors", {}).items():
        lines.append(f"{part}: FAILED: {err.strip().splitlines()[-1]}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda", help="device to check against the CPU (default cuda)")
    p.add_argument("--quick", action="store_true", help="small sizes (B = 4, 160 x 120, N = 300)")
    p.add_argument("--out", type=Path, default=REPO / "scripts" / "results", help="folder of gpu_check.json and .md")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = p.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print("gpu_check: --device cuda: no CUDA device is available to this PyTorch build (use --device cpu --quick)", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    size = QUICK if args.quick else FULL
    result: dict = {"machine": _machine(args.device), "size": dataclasses.asdict(size), "errors": {}}
    t0 = time.perf_counter()
    result["pytest"] = part_pytest(args.device)
    for name, fn in (("agreement", part_agreement), ("timings", part_timings)):
        try:
            result[name] = fn(args.device, size)
        except Exception:  # noqa: BLE001 - one failing part must not hide the others
            result["errors"][name] = traceback.format_exc()
            result[name] = []
    result["wall_s"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gpu_check.json").write_text(json.dumps(result, indent=2) + "\n")
    text = table(result)
    (args.out / "gpu_check.md").write_text(text + "\n")
    print(text)
    failed = bool(result["errors"]) or not all(r["ok"] for r in result["agreement"]) or result["pytest"]["status"].startswith("failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
