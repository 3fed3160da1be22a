"""The ``torchslam`` command line: run, batch, report, eval, info, synth, calibrate-time.

Each subcommand parses its arguments, calls one library function and prints its result.
Errors that torchslam raises on purpose print one line naming the file, line or argument and
exit with status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Sequence as Seq

from .errors import TorchSlamError
from .strictjson import dumps as strict_dumps

logger = logging.getLogger("torchslam")


def _add_threads(p) -> None:
    from .threads import POLICY_THREADS, THREADS_ENV

    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help=f"CPU threads of PyTorch and OpenCV (default: ${THREADS_ENV} if set, else {POLICY_THREADS} for "
                   "PyTorch, which stays fast beside other work, and all cores for OpenCV; see 'Threads' in docs/results/cpu.md)")


def _config_help() -> str:
    from .config import preset_names

    return (
        "YAML file overriding the system's defaults, or the name of a shipped preset: "
        + ", ".join(preset_names())
    )


def _add_run(sub) -> None:
    from .systems.registry import DEFAULT_SYSTEM, KNOWN_SYSTEMS

    p = sub.add_parser(
        "run", help="run a SLAM system on a sequence and write a run folder",
        description="Exit status: 0 when the run folder is written, 1 when some output file could not be "
        "written (the others are kept), 2 for a bad argument, config, data or --out (checked before tracking), "
        "130 when interrupted (the partial run is written, marked interrupted).",
    )
    p.add_argument("--system", default=DEFAULT_SYSTEM, help=f"one of {', '.join(KNOWN_SYSTEMS)} (default {DEFAULT_SYSTEM})")
    p.add_argument("--data", default="synthetic", help="a TUM-layout folder, or 'synthetic' (default) for the built-in sequence")
    p.add_argument("--out", default=None,
                   help="run folder, missing or empty (default logs/<system>-<data>-<time>, a new folder)")
    p.add_argument("--overwrite", action="store_true",
                   help="clear a non-empty --out first; refused unless it holds only files a run writes "
                   "(trajectory.txt, keyframes.txt, map.ply, metrics.json, config.yaml, groundtruth.txt, error.txt, "
                   "TensorBoard events)")
    p.add_argument("--config", default=None, metavar="FILE|PRESET", help=_config_help())
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set kcc.sigma=0.3 (nislam), --set frontend=dense (gcslam) "
                   "or --set data.stride=2 (repeatable)")
    p.add_argument("--params", default=None, metavar="CKPT",
                   help="checkpoint of learned config values (scripts/train.py), applied after --config and before --set")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where tensors live (default cpu)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames (>= 1)")
    p.add_argument("--no-tensorboard", action="store_true", help="do not write TensorBoard event files")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_threads(p)


def _cmd_run(args) -> int:
    from .systems.registry import get_system

    get_system(args.system)  # fail fast, before any data is touched
    from .app.run import RunOptions, default_out_dir, run

    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise _ArgError("--device cuda: no CUDA device is available to this PyTorch build")
    out = Path(args.out) if args.out else default_out_dir(args.system, args.data)
    options = RunOptions(
        system=args.system, data=args.data, out=out, device=args.device,
        tensorboard=not args.no_tensorboard, max_frames=args.max_frames,
        params=Path(args.params) if args.params else None, overwrite=args.overwrite, threads=args.threads,
    )
    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        def progress(frames):
            # disable=None: no bar when stderr is not a terminal (CI logs, redirected output)
            return tqdm(frames, desc=f"{args.system}", unit="frame", leave=False, disable=None)

    from .app.runfolder import OutputWriteError

    try:
        metrics = run(options, config_path=args.config, overrides=args.overrides, progress=progress)
    except OutputWriteError as exc:  # the run was computed; what could be written is kept
        print(f"torchslam run: error: {exc}", file=sys.stderr)
        return 1
    print(_run_line(args.system, metrics))
    print(f"run folder: {out}")
    if metrics.get("interrupted"):
        return 130
    # A run with ground truth whose ATE could not be computed (e.g. non-finite values) failed
    # its evaluation: exit 1, as batch marks such a row "failed".
    return 1 if metrics.get("ate_error") else 0


def _run_line(system: str, metrics: dict) -> str:
    """One line: frames tracked (and on the motion prior), keyframes, the headline ATE, frames/s."""
    ate_m = metrics.get("ate_rmse_m")
    if ate_m is not None:
        ate_txt = f"{ate_m * 100:.2f} cm"
    elif metrics.get("ate_error"):
        ate_txt = f"evaluation failed ({metrics['ate_error']})"
    elif metrics.get("groundtruth"):
        ate_txt = f"n/a ({metrics.get('eval_note', 'not computed')})"
    else:
        ate_txt = "n/a (no ground truth)"
    status = " (interrupted: partial results)" if metrics.get("interrupted") else ""
    prior = metrics.get("prior_frames") or 0
    prior_txt = f", {prior} on motion prior" if prior else ""
    fps, fps_c = metrics.get("fps_end_to_end"), metrics.get("fps_compute")
    fps_txt = "n/a frames/s" if fps is None or fps_c is None else f"{fps:.1f} frames/s end-to-end ({fps_c:.1f} compute-only)"
    return (
        f"{system} on {metrics['sequence']}{status}: {metrics['tracked_frames']}/{metrics['frames']} frames tracked"
        f"{prior_txt}, {metrics['keyframes']} keyframes, ATE RMSE {ate_txt}, {fps_txt}"
    )


def _add_batch(sub) -> None:
    from .systems.registry import DEFAULT_SYSTEM, KNOWN_SYSTEMS

    p = sub.add_parser(
        "batch",
        help="run a SLAM system on many sequences (resumable; shards over torchrun) and write a summary",
        description="Exit status: 0 when every sequence is ok or resumed, 1 when any failed, "
        "2 for a bad argument or config, a folder holding a complete run of another request without "
        "--overwrite, or --out in use by another batch (nothing runs), 130 when interrupted.",
    )
    p.add_argument("sources", nargs="+", metavar="SOURCE",
                   help="a TUM-layout folder, a glob of folders (quoted), 'synthetic' or 'synthetic:K' for K generated sequences")
    p.add_argument("--system", default=DEFAULT_SYSTEM, help=f"one of {', '.join(KNOWN_SYSTEMS)} (default {DEFAULT_SYSTEM})")
    p.add_argument("--out", required=True, help="batch folder: one run folder per sequence plus summary.{md,csv,json}")
    p.add_argument("--batch-size", type=int, default=1,
                   help="sequences per group; groups of a system that supports it run in lockstep (default 1)")
    p.add_argument("--config", default=None, metavar="FILE|PRESET", help=_config_help())
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set data.synthetic.frames=100 (repeatable)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where tensors live (default cpu)")
    p.add_argument("--max-frames", type=int, default=None, help="stop each sequence after this many frames (>= 1)")
    p.add_argument("--no-tensorboard", action="store_true", help="do not write TensorBoard event files")
    p.add_argument("--overwrite", action="store_true",
                   help="redo sequences whose folders hold a complete run of another request (system, data, "
                   "config, --max-frames); without it such a batch is refused. Each old run is replaced only "
                   "once its new run is written")
    _add_threads(p)


def _cmd_batch(args) -> int:
    import os

    from .app.batch import BatchOptions, format_table, run_batch
    from .systems.registry import get_system

    get_system(args.system)  # fail fast, before any data is touched
    options = BatchOptions(
        system=args.system, sources=tuple(args.sources), out=Path(args.out), batch_size=args.batch_size,
        device=args.device, tensorboard=not args.no_tensorboard, max_frames=args.max_frames,
        overwrite=args.overwrite, threads=args.threads,
    )
    rank = f"[rank {os.environ['RANK']}] " if "RANK" in os.environ and os.environ.get("WORLD_SIZE", "1") != "1" else ""

    def on_row(row, done, total):
        ate_m = row["ate_rmse_m"]
        figures = f", ATE {ate_m * 100:.2f} cm" if ate_m is not None else ""
        if row["fps_end_to_end"] is not None and row["status"] == "ok":
            figures += f", {row['fps_end_to_end']:.1f} frames/s"
        note = f": {row['message']}" if row["status"] == "failed" else ""
        print(f"{rank}[{done}/{total}] {row['name']}: {row['status']}{figures}{note}", flush=True)

    result = run_batch(options, config_path=args.config, overrides=args.overrides, on_row=on_row)
    if result.summary_files:
        print()
        print(format_table(result.rows, result.totals), end="")
        print(f"engine: {result.engine}; summary: {result.summary_files[-1]}")
    if result.interrupted:
        return 130
    return 1 if result.failed else 0


def _add_report(sub) -> None:
    p = sub.add_parser("report", help="turn a batch folder into report.md with plots")
    p.add_argument("dir", help="batch folder written by 'torchslam batch'")


def _cmd_report(args) -> int:
    from .app.report import write_report

    path = write_report(args.dir)
    print(f"report: {path}")
    return 0


def _add_eval(sub) -> None:
    p = sub.add_parser(
        "eval", help="ATE/RPE of an estimated trajectory against ground truth (TUM format)",
        description="With the defaults the figures are evo's (evo_ape/evo_rpe tum GT EST -a, delta 1 frame) and "
        "the ATE equals the ate_rmse_m that 'torchslam run' writes to metrics.json for a sequence's raw "
        "groundtruth.txt.",
    )
    p.add_argument("--est", required=True, help="estimated trajectory, TUM format")
    p.add_argument("--gt", required=True, help="ground-truth trajectory, TUM format")
    p.add_argument("--align", default="se3", choices=["se3", "sim3", "none"],
                   help="alignment before ATE and RPE (default se3, as evo's -a; sim3 as -as)")
    p.add_argument("--max-dt", type=float, default=0.01,
                   help="largest timestamp gap when matching poses, seconds (default 0.01, evo's --t_max_diff "
                   "and the headline's)")
    p.add_argument("--association", default="nearest", choices=["nearest", "unique"],
                   help="nearest: evo's nearest-timestamp rule (default, the headline's); unique: the TUM "
                   "benchmark's one-to-one rule")
    p.add_argument("--offset", type=float, default=0.0, help="seconds added to the estimate's stamps before matching (default 0)")
    p.add_argument("--delta", type=float, default=1, help="RPE step (default 1)")
    p.add_argument("--delta-unit", default="frames", choices=["frames", "seconds"], help="unit of --delta (default frames)")
    p.add_argument("--json", action="store_true", help="print strict JSON instead of a table (default: table)")


def _cmd_eval(args) -> int:
    from .data.trajectory import read_tum_trajectory
    from .eval import ate, format_report, metrics_dict, rpe

    est = read_tum_trajectory(args.est)
    gt = read_tum_trajectory(args.gt)
    delta = int(args.delta) if args.delta_unit == "frames" else args.delta
    if args.delta_unit == "frames" and delta != args.delta:
        raise _ArgError(f"--delta {args.delta}: a step in frames must be a whole number")
    match = {"max_dt": args.max_dt, "offset": args.offset, "association": args.association}
    a = ate(est, gt, align=args.align, **match)
    r = rpe(est, gt, delta=delta, unit=args.delta_unit, align=args.align, **match)
    if args.json:
        print(strict_dumps(metrics_dict(a, r)))
    else:
        print(format_report(a, r))
    return 0


def _add_info(sub) -> None:
    p = sub.add_parser("info", help="describe a TUM-layout sequence folder")
    p.add_argument("dir", help="sequence folder")
    p.add_argument("--json", action="store_true", help="print JSON")


def _cmd_info(args) -> int:
    from .data.tum import sequence_info

    info = sequence_info(args.dir)
    if args.json:
        print(strict_dumps(info))
        return 0
    width = max(len(k) for k in info)
    for k, v in info.items():
        if isinstance(v, dict):
            v = ", ".join(f"{kk}={vv}" for kk, vv in v.items())
        elif isinstance(v, float):
            v = f"{v:.6f}" if abs(v) >= 1e5 else f"{v:.6g}"
        print(f"{k:<{width}}  {v}")
    return 0


def _add_synth(sub) -> None:
    p = sub.add_parser("synth", help="write a synthetic RGB-D-inertial sequence as a TUM-layout folder")
    p.add_argument("--out", required=True, help="output folder: new or empty (see --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace what a non-empty --out holds, only if it is a sequence folder that 'torchslam synth' "
                   "wrote (nothing but rgb/, depth/ and its .txt files, calibration.txt its own); anything else is refused")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--trajectory", default=None, help="trajectory kind (see the synthetic generator)")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--no-noise", action="store_true", help="exact depth (no Kinect-like noise or holes)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="any other setting of the generator, e.g. --set period=3.4 --set exposure=0.01 (repeatable; "
                   "applied after the flags above)")


def _cmd_synth(args) -> int:
    from .config import config_from_dict, deep_merge, parse_overrides
    from .data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
    from .threads import setup_threads

    setup_threads()  # rendering is torch work too: the same default (or $TORCHSLAM_THREADS)
    changes = {"frames": args.frames, "seed": args.seed}
    for key in ("trajectory", "width", "height"):
        if getattr(args, key) is not None:
            changes[key] = getattr(args, key)
    if args.no_noise:
        changes["depth_noise"] = False
    changes = deep_merge(changes, parse_overrides(args.overrides))
    cfg = config_from_dict(SyntheticConfig, changes, source="torchslam synth")
    seq = generate_sequence(cfg)
    write_tum_folder(seq, args.out, overwrite=args.overwrite)
    print(f"wrote {len(seq)} frames ({cfg.width}x{cfg.height}, trajectory {cfg.trajectory}, seed {cfg.seed}) to {args.out}")
    return 0


def _add_calibrate_time(sub) -> None:
    p = sub.add_parser(
        "calibrate-time",
        help="estimate NI-SLAM's attitude_time_offset (attitude stream clock vs camera), or with --stream depth "
        "the depth stream's latency (data.depth_time_offset), from the images",
    )
    p.add_argument("--data", default="synthetic", help="a TUM-layout folder, or 'synthetic' (default)")
    p.add_argument("--stream", choices=("attitude", "depth"), default="attitude",
                   help="what to calibrate against the camera: the attitude stream's clock (default), or the depth "
                   "stream's latency against the colour stream (no attitude needed)")
    p.add_argument("--attitude", default="auto", help="attitude source: auto, imu, simulated or groundtruth (default auto)")
    p.add_argument("--max-offset", type=float, default=0.08, help="search [-max, max], seconds (default 0.08)")
    p.add_argument("--pairs", type=int, default=None,
                   help="frame pairs registered (default 60; with --stream depth, frames: default 180)")
    p.add_argument("--frame-gap", type=int, default=3, help="pairs are (i, i + gap) (default 3)")
    p.add_argument("--json", action="store_true", help="print JSON with the whole cost curve")
    _add_threads(p)


def _cmd_calibrate_time(args) -> int:
    from .config import config_from_dict
    from .systems.nislam import NISlamConfig, attitude_stream
    from .app.run import DataConfig, load_sequence
    from .app.calibrate_time import estimate_attitude_time_offset
    from .allocator import setup_allocator
    from .threads import setup_threads

    threads = setup_threads(args.threads)
    allocator = setup_allocator()
    if not args.max_offset > 0:
        raise _ArgError(f"--max-offset {args.max_offset}: expected > 0")
    if (args.pairs is not None and args.pairs < 1) or args.frame_gap < 1:
        raise _ArgError(f"--pairs {args.pairs}, --frame-gap {args.frame_gap}: expected >= 1")
    if args.stream == "depth":
        return _calibrate_depth_time(args, threads, allocator)
    cfg = config_from_dict(NISlamConfig, {"attitude": args.attitude}, source="--attitude")
    seq = load_sequence(args.data, DataConfig(prefetch=0))
    stream = attitude_stream(seq, cfg)
    est = estimate_attitude_time_offset(
        seq, stream, max_offset=args.max_offset, step=min(0.0025, args.max_offset), frame_gap=args.frame_gap,
        max_pairs=60 if args.pairs is None else args.pairs,
    )
    if args.json:
        print(strict_dumps({"sequence": seq.name, "attitude_source": stream.source, **est.to_dict(), **threads.to_dict(), **allocator.to_dict()}))
        return 0
    print(f"sequence          {seq.name}")
    print(f"attitude source   {stream.source}")
    print(f"pairs registered  {est.pairs}")
    print(f"offset            {est.offset * 1000:+.1f} ms")
    print(f"rotation RMS      {est.cost_at_zero:.3f} deg at 0 ms, {est.cost_at_offset:.3f} deg at the offset")
    if est.at_edge:
        print("warning: the minimum lies at the edge of the search range; widen --max-offset")
    print(f"use: torchslam run --system nislam --data {args.data} --set attitude={args.attitude} "
          f"--set attitude_time_offset={est.offset:.4f}")
    return 0


def _calibrate_depth_time(args, threads, allocator) -> int:
    """``calibrate-time --stream depth``: the depth stream's latency (``data.depth_time_offset``)."""
    from .app.calibrate_time import estimate_depth_time_offset
    from .app.run import DataConfig, load_sequence
    from .data.synthetic import SyntheticConfig

    if args.attitude != "auto":
        raise _ArgError(f"--attitude {args.attitude}: the depth latency is measured without an attitude stream; leave --attitude out")
    # The built-in synthetic sequence stamps colour and depth alike: nothing to find there but 0,
    # so a short one serves.
    seq = load_sequence(args.data, DataConfig(prefetch=0, synthetic=SyntheticConfig(frames=120)))
    est = estimate_depth_time_offset(
        seq, frames=180 if args.pairs is None else args.pairs, frame_gap=args.frame_gap, max_offset=args.max_offset,
        step=min(0.0025, args.max_offset),
    )
    if args.json:
        print(strict_dumps({"sequence": seq.name, "stream": "depth", **est.to_dict(), **threads.to_dict(), **allocator.to_dict()}))
        return 0
    print(f"sequence          {seq.name}")
    print("stream            depth (latency against the colour images)")
    print(f"pairs registered  {est.pairs}")
    print(f"offset            {est.offset * 1000:+.1f} ms")
    print(f"rotation RMS      {est.cost_at_zero:.3f} deg at 0 ms, {est.cost_at_offset:.3f} deg at the offset")
    if est.at_edge:
        print("warning: the minimum lies at the edge of the search range; widen --max-offset")
    print(f"use: torchslam run --data {args.data} --set data.depth_time_offset={est.offset:.4f} "
          "(or data.depth_time_offset=auto to estimate it at every run)")
    return 0


class _ArgError(TorchSlamError, ValueError):
    pass


class _SubcommandParser(argparse.ArgumentParser):
    """A subcommand's parser: no abbreviated options, and an unknown option is its own error.

    argparse hands a subcommand's unrecognised arguments back to the top-level parser, which
    would print the top-level usage; this parser reports them with the subcommand's usage
    (exit status 2). Abbreviations are off so that ``--max-frame`` is an error rather than a
    silent ``--max-frames``.
    """

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchslam", description="Batched RGB-D SLAM in PyTorch (GC-SLAM/FastGO, NI-SLAM/KCC).", allow_abbrev=False
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_SubcommandParser)
    for add in (_add_run, _add_batch, _add_report, _add_eval, _add_info, _add_synth, _add_calibrate_time):
        add(sub)
    return parser


COMMANDS = {
    "run": _cmd_run,
    "batch": _cmd_batch,
    "report": _cmd_report,
    "eval": _cmd_eval,
    "info": _cmd_info,
    "synth": _cmd_synth,
    "calibrate-time": _cmd_calibrate_time,
}


def main(argv: Seq[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(levelname)s %(name)s: %(message)s",
    )
    if args.command is None:
        # A bare `torchslam` (top-level options only, e.g. `-v`) runs the default job, as `torchslam run`.
        args = parser.parse_args([*(sys.argv[1:] if argv is None else argv), "run"])
    try:
        status = COMMANDS[args.command](args)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit flush
        return status
    except BrokenPipeError:
        # The reader of our output went away (`torchslam info DIR | head`): stop quietly with the
        # status of a process ended by SIGPIPE, as the shell's own tools do.
        _silence_stdout()
        return EXIT_BROKEN_PIPE
    except TorchSlamError as exc:
        print(f"torchslam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchslam {args.command}: interrupted", file=sys.stderr)
        return 130


# 128 + SIGPIPE: what `cat`, `grep` and other tools report when their reader closes the pipe.
EXIT_BROKEN_PIPE = 141


def _silence_stdout() -> None:
    """Point stdout at the null device so that no later flush raises on the closed pipe."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a real file (captured in tests)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
