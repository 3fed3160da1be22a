"""Benchmark FastGO: linearisation from statistics, full optimisation, and the linear solvers.

Measures, in one run on one machine:

1. **Linearisation** of M pairs as correspondences per pair grow (100 -> 50,000): FastGO
   (:func:`torchslam.fastgo.linearize`, from 28 statistics per pair) against the
   per-correspondence reference (``reference_linearize`` of ``tests/_references.py``, vectorised over
   correspondences), with their ratio measured in the same run.
2. **Full optimisation** to convergence of repeated-route pose graphs
   (:func:`torchslam.fastgo.synthetic.loop_route_problem`: odometry chain, two near-in-time
   pairs and loop pairs to the same place in earlier laps, ~5 pairs per keyframe) for N = 100 ->
   5,000 keyframes from drifted odometry: wall time (symbolic analysis included), iterations,
   peak resident memory added by the call (Linux ``VmHWM`` after resetting it through
   ``/proc/self/clear_refs``) and the size of the sparse factor.
3. **Solvers** on the same normal equations: dense ``torch.linalg.cholesky`` on the full
   ``6N x 6N`` matrix, scipy SuperLU (``splu``, MMD on ``A^T + A``, symmetric mode, diagonal pivots), torchslam's block-sparse
   supernodal Cholesky (analysis and numeric factorisation + solve separately) and block-Jacobi
   PCG (to a 1e-10 relative residual).
4. The same optimisation on CUDA when a GPU is present (skipped otherwise).

Timings are the median (and best) of ``--repeat`` runs; the machine may be shared, so compare
numbers within one run. Writes ``scripts/results/bench_fastgo.json`` and ``bench_fastgo.png``
and prints markdown tables. Usage::

    python scripts/bench_fastgo.py [--quick] [--threads 1] [--repeat 3]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from _bench import REPO_ROOT, test_references, time_calls
from torchslam.fastgo import FastGOConfig, PairStats, assemble, linearize, optimize
from torchslam.fastgo.optimize import FastGOProblem, _prepare
from torchslam.fastgo.synthetic import loop_route_problem
from torchslam.geometry import se3_exp
from torchslam.optim import analyze, block_cholesky, pcg_block_jacobi
from torchslam.environment import cpu_model as _cpu_model

reference_linearize = test_references().reference_linearize


def _time(fn, repeat: int, device="cpu") -> dict:
    t = time_calls(fn, repeat, device)
    return {"median_s": t.median, "best_s": t.best}


def _rss_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _memory_worker(N: int) -> None:
    """Child process: print the peak resident memory one optimisation adds (MiB) as JSON."""
    tiny = _problem(20)
    optimize(tiny.T_init, tiny.pairs, tiny.stats)  # imports and one-time initialisation
    P = _problem(N)
    T0, pairs, stats = P.T_init, P.pairs, P.stats
    del P, tiny
    gc.collect()
    out = {"peak_mib": None, "input_mib": (T0.numel() * 8 + pairs.numel() * 8 + len(stats) * 35 * 8) / 2**20}
    try:
        Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
        base = _rss_kib("VmRSS")
        optimize(T0, pairs, stats)
        peak = _rss_kib("VmHWM")
        out["peak_mib"] = (peak - base) / 1024
    except (OSError, TypeError):
        pass
    print(json.dumps(out))


def _peak_rss_delta_mib(N: int, threads: int) -> dict:
    """Run :func:`_memory_worker` in a fresh process; glibc returns large blocks to the OS there,
    so the resident-set high-water mark follows what the optimisation really holds."""
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536", MALLOC_TRIM_THRESHOLD_="0", OMP_NUM_THREADS=str(threads))
    proc = subprocess.run(
        [sys.executable, __file__, "--memory-worker", str(N), "--threads", str(threads)],
        capture_output=True, text=True, env=env, check=False,
    )
    try:
        return json.loads(proc.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return {"peak_mib": None, "input_mib": None, "error": proc.stderr[-500:]}


# ---------------------------------------------------------------------------------------------


def bench_linearize(ks: list[int], num_pairs: int, repeat: int) -> list[dict]:
    g = torch.Generator().manual_seed(0)
    N = 32
    T = se3_exp(torch.randn(N, 6, generator=g, dtype=torch.float64))
    pairs = torch.stack([torch.randint(0, N, (num_pairs,), generator=g), torch.randint(0, N, (num_pairs,), generator=g)], -1)
    pairs[:, 1] = torch.where(pairs[:, 0] == pairs[:, 1], (pairs[:, 1] + 1) % N, pairs[:, 1])
    rows = []
    for K in ks:
        pi = torch.randn(num_pairs, K, 3, generator=g, dtype=torch.float64) + 2.0
        pj = torch.randn(num_pairs, K, 3, generator=g, dtype=torch.float64)
        stats = PairStats.from_padded(pi, pj)
        fast = _time(lambda: linearize(T, pairs, stats), max(repeat, 20))
        li, lj = list(pi), list(pj)
        ref_rep = repeat if K * num_pairs <= 2_000_000 else 1
        ref = _time(lambda: reference_linearize(T, pairs, li, lj), ref_rep)
        a, b = linearize(T, pairs, stats), reference_linearize(T, pairs, li, lj)
        err = max(float((getattr(a, f) - getattr(b, f)).abs().max() / getattr(b, f).abs().max()) for f in ("H_ii", "H_ij", "H_jj", "g_i", "cost"))
        rows.append({
            "corr_per_pair": K, "pairs": num_pairs, "fastgo_ms": fast["median_s"] * 1e3, "fastgo_best_ms": fast["best_s"] * 1e3,
            "reference_ms": ref["median_s"] * 1e3, "reference_best_ms": ref["best_s"] * 1e3,
            "speedup": ref["median_s"] / fast["median_s"], "max_rel_diff": err,
        })
        print(f"  linearize K={K}: fastgo {rows[-1]['fastgo_ms']:.3f} ms, reference {rows[-1]['reference_ms']:.1f} ms", flush=True)
        del pi, pj, li, lj, stats
        gc.collect()
    return rows


def _problem(N: int, seed: int = 0):
    return loop_route_problem(N, loops_per_keyframe=3, local_pairs=2, correspondences=16, noise=0.01,
                              drift_rot=1e-3, drift_trans=2e-3, seed=seed)


def bench_optimize(ns: list[int], repeat: int, device: str = "cpu", threads: int = 1) -> list[dict]:
    rows = []
    cfg = FastGOConfig()
    for N in ns:
        P = _problem(N)
        T0, pairs, stats = P.T_init.to(device), P.pairs.to(device), P.stats.to(device)
        rep = repeat if N <= 2000 else max(1, repeat // 2)
        t = _time(lambda: optimize(T0, pairs, stats, config=cfg), rep, device)
        res = optimize(T0, pairs, stats, config=cfg)
        memo = _peak_rss_delta_mib(N, threads) if device == "cpu" else {"peak_mib": None, "input_mib": None}
        mem = memo["peak_mib"]
        gpu_mem = None
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
            optimize(T0, pairs, stats, config=cfg)
            gpu_mem = (torch.cuda.max_memory_allocated() - base) / 2**20
        work = _prepare([FastGOProblem(P.T_init, P.pairs, P.stats)], cfg)
        sym = analyze(N, work.pairs[:, 0], work.pairs[:, 1], work.fixed, 6, cfg.leaf_size, cfg.ordering)
        rows.append({
            "keyframes": N, "pairs": int(pairs.shape[0]), "device": device, "time_ms": t["median_s"] * 1e3,
            "best_ms": t["best_s"] * 1e3, "iterations": res.iterations, "converged": res.converged,
            "cost_first": float(res.cost[0]), "cost_last": float(res.cost[-1]), "peak_rss_mib": mem,
            "peak_cuda_mib": gpu_mem, "input_mib": memo["input_mib"], "factor_nnz": sym.factor_nnz, "fronts": sym.num_fronts,
        })
        print(f"  optimize N={N} ({device}): {rows[-1]['time_ms']:.1f} ms, {res.iterations} it, mem {mem}", flush=True)
    return rows


def _scipy_splu(H, free):
    import scipy.sparse as sp

    n, b = H.num_nodes, 6
    r = torch.cat([torch.arange(n), H.rows, H.cols])
    c = torch.cat([torch.arange(n), H.cols, H.rows])
    blocks = torch.cat([H.diag, H.off, H.off.transpose(-1, -2)]).numpy()
    ii = (r.numpy()[:, None, None] * b + np.arange(b)[None, :, None] + 0 * np.arange(b)[None, None, :]).ravel()
    jj = (c.numpy()[:, None, None] * b + 0 * np.arange(b)[None, :, None] + np.arange(b)[None, None, :]).ravel()
    A = sp.csc_matrix((blocks.ravel(), (ii, jj)), shape=(n * b, n * b))
    dof = np.repeat(free.numpy(), b)
    return A[dof][:, dof].tocsc(), dof


def bench_solvers(ns: list[int], repeat: int, dense_max: int) -> list[dict]:
    import scipy.sparse.linalg as spla

    rows = []
    cfg = FastGOConfig()
    for N in ns:
        P = _problem(N)
        work = _prepare([FastGOProblem(P.T_init, P.pairs, P.stats)], cfg)
        H, g = assemble(linearize(work.T, work.pairs, work.stats), work.pairs, N)
        rhs = -g
        free = ~work.fixed
        row = {"keyframes": N, "pairs": int(work.pairs.shape[0])}
        sym_t = _time(lambda: analyze(N, H.rows, H.cols, work.fixed, 6, cfg.leaf_size, cfg.ordering), repeat)
        sym = analyze(N, H.rows, H.cols, work.fixed, 6, cfg.leaf_size, cfg.ordering)
        num_t = _time(lambda: block_cholesky(H, sym).solve(rhs), repeat)
        x_ref = block_cholesky(H, sym).solve(rhs)
        row.update(block_analyze_ms=sym_t["median_s"] * 1e3, block_factor_solve_ms=num_t["median_s"] * 1e3)
        A, dof = _scipy_splu(H, free)
        b = rhs.reshape(-1).numpy()[dof]
        lu_t = _time(lambda: spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}).solve(b), repeat)
        xs = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}).solve(b)
        row.update(superlu_ms=lu_t["median_s"] * 1e3,
                   superlu_vs_block_max_diff=float(np.abs(xs - x_ref.reshape(-1).numpy()[dof]).max()))
        if N <= dense_max:
            D = torch.as_tensor(A.toarray())
            dn_t = _time(lambda: torch.cholesky_solve(torch.as_tensor(b)[:, None], torch.linalg.cholesky(D)), max(1, repeat // 2))
            row["dense_ms"] = dn_t["median_s"] * 1e3
        else:
            row["dense_ms"] = None
        t0 = time.perf_counter()
        xp, conv, its = pcg_block_jacobi(H, rhs, work.fixed, tol=1e-10, max_iter=3000)
        row.update(pcg_ms=(time.perf_counter() - t0) * 1e3, pcg_iterations=its, pcg_converged=bool(conv))
        rows.append(row)
        print(f"  solvers N={N}: block {row['block_analyze_ms']:.1f}+{row['block_factor_solve_ms']:.1f} ms, superlu {row['superlu_ms']:.1f} ms, dense {row['dense_ms']}, pcg {row['pcg_ms']:.0f} ms/{its} it", flush=True)
    return rows


# ---------------------------------------------------------------------------------------------


def _fmt(v, nd=1):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def tables(res: dict) -> str:
    out = ["### Linearisation (M = %d pairs)" % res["linearize"][0]["pairs"], "",
           "| corr/pair | FastGO ms | reference ms | speed-up | max rel. diff |", "|---:|---:|---:|---:|---:|"]
    for r in res["linearize"]:
        out.append(f"| {r['corr_per_pair']:,} | {r['fastgo_ms']:.3f} | {r['reference_ms']:.1f} | {r['speedup']:.0f}x | {r['max_rel_diff']:.1e} |")
    out += ["", "### Full optimisation to convergence", "",
            "| keyframes | pairs | device | time ms (median) | best ms | iterations | peak memory MiB | input MiB | factor nnz |",
            "|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in res["optimize"] + res.get("optimize_cuda", []):
        mem = r["peak_rss_mib"] if r["peak_rss_mib"] is not None else r.get("peak_cuda_mib")
        out.append(f"| {r['keyframes']:,} | {r['pairs']:,} | {r['device']} | {r['time_ms']:.1f} | {r['best_ms']:.1f} | {r['iterations']} | {_fmt(mem)} | {_fmt(r.get('input_mib'))} | {r['factor_nnz']:,} |")
    out += ["", "### Linear solvers (one Gauss-Newton system)", "",
            "| keyframes | pairs | dense Cholesky ms | SuperLU ms | block Cholesky analyse + factor/solve ms | PCG ms (iterations) |",
            "|---:|---:|---:|---:|---:|---:|"]
    for r in res["solvers"]:
        out.append(f"| {r['keyframes']:,} | {r['pairs']:,} | {_fmt(r['dense_ms'])} | {r['superlu_ms']:.1f} | {r['block_analyze_ms']:.1f} + {r['block_factor_solve_ms']:.1f} | {r['pcg_ms']:.0f} ({r['pcg_iterations']}{'' if r['pcg_converged'] else ', not converged'}) |")
    return "\n".join(out)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    L = res["linearize"]
    k = [r["corr_per_pair"] for r in L]
    ax[0].loglog(k, [r["fastgo_ms"] for r in L], "o-", label="FastGO (statistics)")
    ax[0].loglog(k, [r["reference_ms"] for r in L], "s-", label="per-correspondence reference")
    ax[0].set_xlabel("correspondences per pair")
    ax[0].set_ylabel("linearisation time [ms]")
    ax[0].set_title(f"Linearisation, {L[0]['pairs']} pairs")
    ax[0].legend()
    O = res["optimize"]
    n = [r["keyframes"] for r in O]
    ax[1].loglog(n, [r["time_ms"] for r in O], "o-", label="CPU time to convergence")
    if res.get("optimize_cuda"):
        C = res["optimize_cuda"]
        ax[1].loglog([r["keyframes"] for r in C], [r["time_ms"] for r in C], "^-", label="CUDA")
    ax[1].set_xlabel("keyframes N (~5 pairs each)")
    ax[1].set_ylabel("time [ms]")
    ax[1].set_title("Full optimisation")
    mem = [r["peak_rss_mib"] for r in O]
    if all(m is not None for m in mem):
        tw = ax[1].twinx()
        tw.loglog(n, mem, "x--", color="tab:red", label="peak memory added [MiB]")
        tw.set_ylabel("peak memory added [MiB]", color="tab:red")
        tw.legend(loc="lower right")
    ax[1].legend(loc="upper left")
    S = res["solvers"]
    ns = [r["keyframes"] for r in S]
    dn = [(r["keyframes"], r["dense_ms"]) for r in S if r["dense_ms"] is not None]
    if dn:
        ax[2].loglog(*zip(*dn), "o-", label="dense Cholesky")
    ax[2].loglog(ns, [r["superlu_ms"] for r in S], "s-", label="scipy SuperLU")
    ax[2].loglog(ns, [r["block_factor_solve_ms"] for r in S], "^-", label="block Cholesky (numeric)")
    ax[2].loglog(ns, [r["block_factor_solve_ms"] + r["block_analyze_ms"] for r in S], "v--", label="block Cholesky (+ analysis)")
    ax[2].loglog(ns, [r["pcg_ms"] for r in S], "d-", label="block-Jacobi PCG")
    ax[2].set_xlabel("keyframes N")
    ax[2].set_ylabel("solve time [ms]")
    ax[2].set_title("One normal-equation solve")
    ax[2].legend(fontsize=8)
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, one repeat (smoke run)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: the machine is shared)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=128, help="pairs in the linearisation sweep")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "scripts" / "results")
    ap.add_argument("--memory-worker", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.memory_worker is not None:
        _memory_worker(args.memory_worker)
        return
    if args.quick:
        ks, ns, ns_solve, repeat, pairs = [100, 1000, 3000], [100, 600], [100, 600], 1, 32
    else:
        ks = [100, 300, 1000, 3000, 10000, 50000]
        ns, ns_solve, repeat, pairs = [100, 300, 600, 1000, 2000, 5000], [100, 300, 600, 1000, 2000, 5000], args.repeat, args.pairs
    start = time.perf_counter()
    load0 = list(os.getloadavg())
    print("linearisation sweep", flush=True)
    res = {"linearize": bench_linearize(ks, pairs, repeat)}
    print("optimisation sweep", flush=True)
    res["optimize"] = bench_optimize(ns, repeat, threads=args.threads)
    print("solver comparison", flush=True)
    res["solvers"] = bench_solvers(ns_solve, repeat, dense_max=1000)
    if torch.cuda.is_available():
        res["optimize_cuda"] = bench_optimize(ns, repeat, "cuda")
    else:
        res["cuda"] = "skipped: no CUDA device"
    res["machine"] = {
        "cpu": _cpu_model(), "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
        "loadavg_start": load0, "loadavg_end": list(os.getloadavg()), "quick": args.quick,
        "wall_s": time.perf_counter() - start,
        "problem": "loop_route_problem(N, loops_per_keyframe=3, local_pairs=2, correspondences=16, noise=0.01 m, "
                   "drift 1e-3 rad / 2 mm per step), 4 laps",
        "config": {k: str(v) for k, v in vars(FastGOConfig()).items()},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_fastgo.json").write_text(json.dumps(res, indent=2))
    plot(res, args.out / "bench_fastgo.png")
    print()
    print(tables(res))
    print(f"\nload average {load0} -> {res['machine']['loadavg_end']}; wrote {args.out / 'bench_fastgo.json'} and .png")


if __name__ == "__main__":
    main()
