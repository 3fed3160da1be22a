"""Train learnable torchslam parameters and compare them with the defaults on held-out data.

``--what kcc``: NI-SLAM's KCC σ, λ and soft arg-max temperature on keyframe/frame pairs of
synthetic sequences (training seeds), validated on other seeds and, with ``--tum DIR``, on
frame pairs of a real TUM-layout sequence with ground truth. The checkpoint's values apply to
``torchslam run --system nislam --params DIR/params.pt``.

``--what features``: NI-SLAM's learned KCC channels (``kcc.features=learned``), a small
convolutional network trained end to end through the correlator (soft arg-max shift and a
PSR-shaped term) on synthetic keyframe/frame pairs only, picked by held-out synthetic seeds. Its
checkpoint (``kind: module``, ``KCCFeatureNet``) applies to ``torchslam run --system nislam
--params DIR/params.pt``; the weights that ship in ``torchslam/kcc/weights/`` came from this
command at its defaults.

``--what pairnet``: the FastGO pair-weight network, trained by unrolling FastGO on synthetic
pose graphs with planted false loop pairs and validated on held-out graphs. Its checkpoint holds
network weights (``kind: module``), not config values.

Writes into ``--out DIR``: TensorBoard event files (loss, parameters, validation figures),
``params.pt`` (``torchslam.learn.save_checkpoint``), ``metrics.json`` and ``history.json`` (the
logged scalars per step; ``--what features`` also plots them in ``curve.png``); prints the comparison
of learned against default values. Usage::

    python scripts/train.py --what kcc --out logs/train-kcc [--steps 60] [--tum ../shared/data/tum_fr1_xyz --tum-frames 300]
    python scripts/train.py --what features --out logs/train-features [--threads 2]
    python scripts/train.py --what pairnet --out logs/train-pairnet
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import torch

from torchslam.config import config_from_dict, config_to_dict, parse_overrides
from torchslam.errors import TorchSlamError
from torchslam.learn import (
    FeatureTrainConfig,
    KCCTrainConfig,
    PairNetTrainConfig,
    save_checkpoint,
    train_features,
    train_kcc,
    train_pairnet,
)
from torchslam.systems.monitor import TensorBoardMonitor


def _seeds(text: str) -> tuple[int, ...]:
    """``"0-7"`` or ``"0,3,5"`` (or a mix) as a tuple of ints."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return tuple(out)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--what", required=True, choices=["kcc", "features", "pairnet"], help="what to train")
    p.add_argument("--out", required=True, help="output folder (TensorBoard, params.pt, metrics.json)")
    p.add_argument("--steps", type=int, default=None, help="optimiser steps (default: the training config's)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default: the training config's)")
    p.add_argument("--train-seeds", type=_seeds, default=None, help="training seeds, e.g. 0-7")
    p.add_argument("--val-seeds", type=_seeds, default=None, help="held-out seeds, e.g. 100-103")
    p.add_argument("--batch-size", type=int, default=None, help="pairs (kcc, features) or graphs (pairnet) per step; 0 = all (kcc)")
    p.add_argument("--seed", type=int, default=None, help="features: seed of the initialisation and batches (default 0)")
    p.add_argument("--tum", default=None, help="kcc: also validate on frame pairs of this TUM-layout folder")
    p.add_argument("--tum-frames", type=int, default=None, help="kcc: frames of --tum used from its start (default 60)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="any other field of the training config (KCCTrainConfig, FeatureTrainConfig, PairNetTrainConfig), "
                        "e.g. --set hidden=4 --set gaps=[3,8]; repeatable")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress")
    return p


def _overrides(args) -> dict:
    out = dict(parse_overrides(args.sets))
    for key, attr in (("steps", "steps"), ("lr", "lr"), ("train_seeds", "train_seeds"), ("val_seeds", "val_seeds"),
                      ("batch_size", "batch_size")):
        if getattr(args, attr) is not None:
            out[key] = getattr(args, attr)
    return out


def _line(name: str, a: dict, b: dict, keys: tuple[str, ...]) -> str:
    return f"{name:<34}" + "  ".join(f"{k} {a[k]:.4g} -> {b[k]:.4g}" for k in keys)


def plot_history(history: list[dict], metrics: dict, path: Path) -> None:
    """The training curve of ``--what features``: training loss per step, held-out error per evaluation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [(h["step"], h["train/loss"]) for h in history if "train/loss" in h]
    val = [(h["step"], h["val/median_px"], h["val/score_px2"]) for h in history if "val/median_px" in h]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    if train:
        steps, loss = zip(*train)
        k = max(1, len(loss) // 30)  # a running mean over ~1/30 of the run
        smooth = [sum(loss[max(0, i - k + 1): i + 1]) / len(loss[max(0, i - k + 1): i + 1]) for i in range(len(loss))]
        axes[0].plot(steps, loss, color="tab:blue", alpha=0.25, lw=0.8, label="per step")
        axes[0].plot(steps, smooth, color="tab:blue", label=f"running mean ({k} steps)")
        axes[0].set_xlabel("step")
        axes[0].set_ylabel("training objective (px², robust)")
        axes[0].set_yscale("log")
        axes[0].legend()
    if val:
        steps, med, score = zip(*val)
        hc = metrics["val_handcrafted"]
        axes[1].plot(steps, med, "o-", color="tab:green", label="learned: median shift error (px)")
        axes[1].axhline(hc["median_px"], color="tab:green", ls="--", label="hand-crafted: median (px)")
        axes[1].plot(steps, score, "s-", color="tab:red", label="learned: truncated MSE (px²)")
        axes[1].axhline(hc["score_px2"], color="tab:red", ls="--", label="hand-crafted: truncated MSE (px²)")
        axes[1].axvline(metrics["best_step"], color="grey", lw=0.8)
        axes[1].set_xlabel("step")
        axes[1].set_title(f"{metrics['val_pairs']} held-out synthetic pairs", fontsize=9)
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if (args.tum or args.tum_frames) and args.what != "kcc":
        parser.error("--tum and --tum-frames apply to --what kcc only (features train on synthetic data only)")
    if args.seed is not None and args.what != "features":
        parser.error("--seed applies to --what features only")
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    monitor = TensorBoardMonitor(out)
    start = time.perf_counter()
    try:
        if args.what == "kcc":
            tum = {"tum": args.tum} if args.tum_frames is None else {"tum": args.tum, "tum_frames": args.tum_frames}
            cfg = config_from_dict(KCCTrainConfig, {**_overrides(args), **tum}, source="--set")
            result = train_kcc(cfg, monitor=monitor)
            extra = {"what": "kcc", "system": "nislam", "train_config": config_to_dict(cfg)}
        elif args.what == "features":
            over = _overrides(args)
            if args.seed is not None:
                over["seed"] = args.seed
            cfg = config_from_dict(FeatureTrainConfig, over, source="--set")
            result = train_features(cfg, monitor=monitor)
            extra = {"what": "features", "system": "nislam", "train_config": config_to_dict(cfg),
                     "architecture": result.module.architecture()}
        else:
            cfg = config_from_dict(PairNetTrainConfig, _overrides(args), source="--set")
            result = train_pairnet(cfg, monitor=monitor)
            extra = {"what": "pairnet", "system": "gcslam", "train_config": config_to_dict(cfg),
                     "architecture": result.module.architecture()}
    except TorchSlamError as exc:
        print(f"train.py: error: {exc}", file=sys.stderr)
        return 2
    finally:
        monitor.close()
    m = result.metrics
    m["seconds"] = time.perf_counter() - start
    m["torch_threads"] = args.threads
    extra["metrics"] = json.loads(json.dumps(m))
    (out / "history.json").write_text(json.dumps(result.history))
    if args.what == "features":
        plot_history(result.history, m, out / "curve.png")
    ckpt = save_checkpoint(out / "params.pt", result.module, extra)
    (out / "metrics.json").write_text(json.dumps({"what": args.what, "train_config": extra["train_config"], **m}, indent=2))
    if args.what == "kcc":
        print(f"trained on {m['train_pairs']} pairs, validated on {m['val_pairs']} held-out pairs ({m['seconds']:.0f} s)")
        print(_line("values (default -> learned)", m["default"], m["learned"], ("sigma", "lam", "temperature")))
        print(f"{'train soft-argmax loss, px^2':<34}{m['train_loss_default']:.4g} -> {m['train_loss_learned']:.4g}")
        keys = ("soft_loss_px2", "rms_px", "rms_mm", "fail_rate")
        print(_line("validation (synthetic)", m["val_default"], m["val_learned"], keys))
        if "tum_default" in m:
            print(_line(f"validation ({Path(args.tum).name}, {m['tum_pairs']} pairs)", m["tum_default"], m["tum_learned"], keys))
    elif args.what == "features":
        print(f"trained on {m['train_pairs']} synthetic pairs, picked at step {m['best_step']} by {m['val_pairs']} "
              f"held-out pairs ({m['seconds']:.0f} s, {m['parameters']} parameters)")
        keys = ("score_px2", "median_px", "fail_rate", "median_psr")
        print(_line("validation (hand-crafted -> learned)", m["val_handcrafted"], m["val_learned"], keys))
    else:
        print(f"trained on {m['train_graphs']} graphs, validated on {m['val_graphs']} held-out graphs ({m['seconds']:.0f} s)")
        print(_line("validation (unit weights -> net)", m["val_unit"], m["val_learned"], ("rms_m", "weight_false", "weight_true")))
        print(f"{'reference: FastGO robust cauchy':<34}rms_m {m['val_cauchy_rms_m']:.4g}")
    print(f"checkpoint: {ckpt}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
