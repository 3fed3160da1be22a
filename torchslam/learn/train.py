"""Training loops: KCC σ, λ and temperature (NI-SLAM), and the FastGO pair-weight network.

Both fit on training seeds of synthetic data, evaluate on held-out seeds and report against the
untrained baseline (the paper's σ = 0.2, λ = 0.1; FastGO with every pair weighted 1). Scalars go
to an injected :class:`~torchslam.systems.monitor.Monitor` (TensorBoard in ``scripts/train.py``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch

from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, check_limits
from ..fastgo import FastGOConfig, FastGOProblem, optimize_batch
from ..systems.monitor import Monitor
from ..systems.nislam import NISlamConfig
from .kcc import KCCPairs, kcc_pair_errors, kcc_shift_loss, resized_kcc_config, synthetic_kcc_pairs, tum_kcc_pairs
from .pairnet import (
    FalseLoopProblem,
    PairWeightNet,
    false_loop_problem,
    pair_features,
    pose_error,
    rms_translation_error,
    weighted_optimize,
)
from .params import LearnableParams, learnable

__all__ = [
    "KCCTrainConfig",
    "PairNetTrainConfig",
    "TrainResult",
    "evaluate_kcc",
    "evaluate_pairnet",
    "train_kcc",
    "train_pairnet",
]

logger = logging.getLogger(__name__)

KCC_KEYS = ("kcc.sigma", "kcc.lam", "kcc.temperature")


def _check_training(cfg) -> None:
    """Checks shared by the training configs: declared limits, disjoint, non-empty seed sets."""
    check_limits(cfg)
    if set(cfg.train_seeds) & set(cfg.val_seeds):
        raise ConfigError(f"val_seeds: must not overlap train_seeds, both hold {sorted(set(cfg.train_seeds) & set(cfg.val_seeds))}")
    if not cfg.train_seeds or not cfg.val_seeds:
        raise ConfigError("train_seeds, val_seeds: expected at least one seed each")


@dataclass(frozen=True)
class KCCTrainConfig:
    """Settings of :func:`train_kcc`.

    Attributes:
        names: config keys to learn (dotted keys of ``NISlamConfig``).
        train_seeds: synthetic sequence seeds to train on.
        val_seeds: held-out seeds to validate on.
        frames: frames per synthetic sequence.
        keyframe_step: frames between keyframes of the pairs.
        gaps: frame steps from a keyframe to its frame (cycled).
        width: rendered width, pixels.
        height: rendered height, pixels.
        ortho_height: orthographic image height used for training and validation.
        ortho_width: orthographic image width.
        steps: Adam steps.
        lr: Adam learning rate (on log σ, log λ, log temperature).
        batch_size: pairs per step (0: all training pairs every step).
        seed: seed of the mini-batch sampling.
        eval_every: validate every this many steps.
        tum: optional TUM-layout folder with ground truth for a second validation set.
        tum_frames: frames of ``tum`` used (from its start).
    """

    names: tuple[str, ...] = KCC_KEYS
    train_seeds: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7)
    val_seeds: tuple[int, ...] = (100, 101, 102, 103)
    frames: int = 60
    keyframe_step: int = 5
    gaps: tuple[int, ...] = (3, 6, 9, 12)
    width: int = 320
    height: int = 240
    ortho_height: int = 180
    ortho_width: int = 240
    steps: int = 60
    lr: float = 0.05
    batch_size: int = 0
    seed: int = 0
    eval_every: int = 10
    tum: str | None = None
    tum_frames: int = 60

    LIMITS: ClassVar[dict[str, Limit]] = {
        "train_seeds": Limit(), "val_seeds": Limit(), "frames": AT_LEAST_1, "keyframe_step": AT_LEAST_1,
        "gaps": AT_LEAST_1, "width": AT_LEAST_1, "height": AT_LEAST_1, "ortho_height": AT_LEAST_1, "ortho_width": AT_LEAST_1,
        "steps": AT_LEAST_1, "lr": POSITIVE, "batch_size": NON_NEGATIVE, "seed": Limit(), "eval_every": AT_LEAST_1,
        "tum_frames": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        unknown = [k for k in self.names if k not in KCC_KEYS]
        if unknown or not self.names:
            raise ConfigError(f"names: the KCC objective learns some of {list(KCC_KEYS)}, got {list(self.names)}")
        _check_training(self)


@dataclass
class TrainResult:
    """What a training run produced.

    Attributes:
        module: the trained parameters (``LearnableParams``) or network (``PairWeightNet``).
        metrics: final figures: baseline against learned, on training and validation data.
        history: per-step scalars (``step`` and the logged values).
    """

    module: torch.nn.Module
    metrics: dict[str, Any]
    history: list[dict[str, float]] = field(default_factory=list)


def _rms_px(err_m, pairs: KCCPairs) -> float:
    return math.sqrt(float((err_m / pairs.resolution[:, None]).square().sum(1).mean()))


def evaluate_kcc(pairs: KCCPairs, kcc_cfg, sigma: float, lam: float, temperature: float) -> dict[str, float]:
    """Validation figures of σ, λ, temperature on pairs.

    Returns:
        ``soft_loss_px2`` (the training objective), ``rms_px`` and ``rms_mm`` of the shift a plain
        run measures (hard peak, ``kcc_cfg.subpixel``), ``median_mm`` and ``fail_rate``
        (fraction of pairs off by more than 2 px).
    """
    with torch.no_grad():
        soft = float(kcc_shift_loss(pairs, sigma, lam, temperature, kcc_cfg).loss)
    err = kcc_pair_errors(pairs, dataclasses.replace(kcc_cfg, soft_argmax=False), sigma, lam)
    px = (err / pairs.resolution[:, None]).norm(dim=1)
    mm = err.norm(dim=1) * 1000
    return {
        "soft_loss_px2": soft,
        "rms_px": _rms_px(err, pairs),
        "rms_mm": math.sqrt(float(mm.square().mean())),
        "median_mm": float(mm.median()),
        "fail_rate": float((px > 2).to(torch.float64).mean()),
    }


def _kcc_data(cfg: KCCTrainConfig, kcc_cfg, seeds) -> KCCPairs:
    return synthetic_kcc_pairs(seeds, kcc_cfg, cfg.frames, cfg.keyframe_step, cfg.gaps, cfg.width, cfg.height)


def train_kcc(cfg: KCCTrainConfig | None = None, base: NISlamConfig | None = None, monitor: Monitor | None = None) -> TrainResult:
    """Fit NI-SLAM's KCC σ, λ and soft arg-max temperature to synthetic keyframe/frame pairs.

    The objective is :func:`~torchslam.learn.kcc.kcc_shift_loss` (soft arg-max ``t_xy`` squared
    error in pixels) minimised with Adam on the log-parameters.

    Args:
        cfg: training settings.
        base: the NI-SLAM config whose values start the training (defaults: the paper's).
        monitor: where scalars go.

    Returns:
        TrainResult with a ``LearnableParams`` over ``NISlamConfig`` (``cfg.names``) and metrics
        ``train/…``, ``val_default/…``, ``val_learned/…`` (and ``tum_…`` with ``cfg.tum``).
    """
    cfg = cfg or KCCTrainConfig()
    base = base or NISlamConfig()
    monitor = monitor or Monitor()
    params = learnable(base, cfg.names)
    kcc_cfg = resized_kcc_config(base.kcc, cfg.ortho_height, cfg.ortho_width)
    logger.info("rendering %d training and %d validation sequences", len(cfg.train_seeds), len(cfg.val_seeds))
    train = _kcc_data(cfg, kcc_cfg, cfg.train_seeds)
    val = _kcc_data(cfg, kcc_cfg, cfg.val_seeds)
    tum = tum_kcc_pairs(cfg.tum, kcc_cfg, 0, cfg.tum_frames, cfg.keyframe_step, cfg.gaps) if cfg.tum else None

    def values(p: LearnableParams) -> dict[str, Any]:
        return {k: p.resolve(base, f"kcc.{k}") for k in ("sigma", "lam", "temperature")}

    def floats(p: LearnableParams) -> dict[str, float]:
        return {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in values(p).items()}

    default = {k: float(getattr(base.kcc, k)) for k in ("sigma", "lam", "temperature")}
    metrics: dict[str, Any] = {"train_pairs": len(train), "val_pairs": len(val), "default": default}
    metrics["val_default"] = evaluate_kcc(val, kcc_cfg, **default)
    if tum is not None:
        metrics["tum_pairs"] = len(tum)
        metrics["tum_default"] = evaluate_kcc(tum, kcc_cfg, **default)
    opt = torch.optim.Adam(params.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    history = []
    for step in range(cfg.steps + 1):
        if step % cfg.eval_every == 0 or step == cfg.steps:
            v = floats(params)
            ev = evaluate_kcc(val, kcc_cfg, **v)
            monitor.scalars(ev, step, prefix="val/")
            monitor.scalars(v, step, prefix="params/")
            history.append({"step": step, **{f"val/{k}": x for k, x in ev.items()}, **v})
            if tum is not None:
                ev_tum = evaluate_kcc(tum, kcc_cfg, **v)
                monitor.scalars(ev_tum, step, prefix="tum/")
                history[-1].update({f"tum/{k}": x for k, x in ev_tum.items()})
        if step == cfg.steps:
            # The last evaluation is of the learned values: it is the result.
            metrics["val_learned"] = ev
            if tum is not None:
                metrics["tum_learned"] = ev_tum
            break
        batch = train
        if 0 < cfg.batch_size < len(train):
            batch = train.select(torch.randperm(len(train), generator=gen)[: cfg.batch_size])
        out = kcc_shift_loss(batch, **values(params), cfg=kcc_cfg)
        opt.zero_grad()
        out.loss.backward()
        opt.step()
        loss = float(out.loss.detach())
        monitor.scalar("train/loss_px2", loss, step)
        if step == 0:
            metrics["train_loss_first"] = loss
        metrics["train_loss_last"] = loss
    learned = floats(params)
    metrics["learned"] = learned
    with torch.no_grad():
        metrics["train_loss_default"] = float(kcc_shift_loss(train, **default, cfg=kcc_cfg).loss)
        metrics["train_loss_learned"] = float(kcc_shift_loss(train, **learned, cfg=kcc_cfg).loss)
    monitor.hparams({k: float(v) for k, v in learned.items()},
                    {"val_rms_px": metrics["val_learned"]["rms_px"], "val_soft_loss_px2": metrics["val_learned"]["soft_loss_px2"]})
    return TrainResult(params, metrics, history)


# ----------------------------------------------------------------------------------------------
# FastGO pair weights


@dataclass(frozen=True)
class PairNetTrainConfig:
    """Settings of :func:`train_pairnet`.

    Attributes:
        train_seeds: seeds of the training graphs.
        val_seeds: seeds of the held-out graphs.
        num_keyframes: keyframes per graph.
        lap_length: keyframes per lap of the route.
        num_false: planted false loop pairs per graph.
        noise: correspondence noise, metres.
        unroll: LM iterations unrolled per training step.
        steps: Adam steps.
        lr: Adam learning rate.
        hidden: hidden width of the network.
        batch_size: graphs per step (0: all).
        seed: seed of the network initialisation and the graph sampling.
        eval_every: validate every this many steps.
        eval_iterations: LM iterations (to convergence) of the validation solves.
    """

    train_seeds: tuple[int, ...] = tuple(range(16))
    val_seeds: tuple[int, ...] = tuple(range(100, 108))
    num_keyframes: int = 24
    lap_length: int = 8
    num_false: int = 3
    noise: float = 0.01
    unroll: int = 5
    steps: int = 60
    lr: float = 0.01
    hidden: int = 16
    batch_size: int = 8
    seed: int = 0
    eval_every: int = 10
    eval_iterations: int = 30

    LIMITS: ClassVar[dict[str, Limit]] = {
        "train_seeds": Limit(), "val_seeds": Limit(), "num_keyframes": Limit(ge=2), "lap_length": AT_LEAST_1,
        "num_false": NON_NEGATIVE, "noise": NON_NEGATIVE, "unroll": AT_LEAST_1, "steps": AT_LEAST_1, "lr": POSITIVE,
        "hidden": AT_LEAST_1, "batch_size": NON_NEGATIVE, "seed": Limit(), "eval_every": AT_LEAST_1,
        "eval_iterations": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        _check_training(self)


def _graphs(cfg: PairNetTrainConfig, seeds) -> list[FalseLoopProblem]:
    return [false_loop_problem(int(s), cfg.num_keyframes, cfg.lap_length, cfg.num_false, cfg.noise) for s in seeds]


def evaluate_pairnet(net: PairWeightNet | None, graphs: list[FalseLoopProblem], iterations: int = 30) -> dict[str, float]:
    """Validation figures of pair weights on graphs, solved to convergence.

    Args:
        net: the network, or None for weight 1 on every pair (plain FastGO).
        graphs: graphs with planted false pairs.
        iterations: LM iterations.

    Returns:
        ``rms_m`` (RMS keyframe position error over graphs, metres), ``pose_error`` (mean of
        :func:`pose_error`), ``weight_false`` and ``weight_true`` (mean weights of the planted
        false and of the true pairs).
    """
    with torch.no_grad():
        weights = None if net is None else [net(pair_features(g.T_init, g.pairs, g.stats)) for g in graphs]
        T = weighted_optimize(graphs, weights, iterations, unrolled=False)
    w = torch.cat(weights) if weights is not None else torch.ones(sum(len(g.false) for g in graphs), dtype=torch.float64)
    false = torch.cat([g.false for g in graphs])
    return {
        "rms_m": rms_translation_error(torch.cat(list(T)), torch.cat([g.T_gt for g in graphs])),
        "pose_error": float(sum(pose_error(t, g.T_gt) for t, g in zip(T, graphs)) / len(graphs)),
        "weight_false": float(w[false].mean()) if bool(false.any()) else math.nan,
        "weight_true": float(w[~false].mean()),
    }


def _robust_rms(graphs: list[FalseLoopProblem], kernel: str, scale: float, iterations: int) -> float:
    """RMS position error of FastGO's own robust pair re-weighting (a reference, not learned)."""
    cfg = FastGOConfig(iterations=iterations, robust=kernel, robust_scale=scale)
    res = optimize_batch([FastGOProblem(g.T_init, g.pairs, g.stats) for g in graphs], cfg)
    return rms_translation_error(res.T_wc, torch.cat([g.T_gt for g in graphs]))


def train_pairnet(cfg: PairNetTrainConfig | None = None, monitor: Monitor | None = None) -> TrainResult:
    """Train :class:`PairWeightNet` by unrolling FastGO on graphs with planted false loops.

    Each step weights the pairs of a batch of training graphs by the network, runs ``cfg.unroll``
    LM iterations (one batched ``optimize_batch``), and descends the mean :func:`pose_error`
    against ground truth through the unrolled iterations.

    Args:
        cfg: training settings.
        monitor: where scalars go.

    Returns:
        TrainResult with the network and metrics ``val_unit`` (every weight 1), ``val_learned``,
        ``val_cauchy_rms_m`` (FastGO's robust re-weighting, for reference) and training losses.
    """
    cfg = cfg or PairNetTrainConfig()
    monitor = monitor or Monitor()
    torch.manual_seed(cfg.seed)  # the network's initial weights
    net = PairWeightNet(cfg.hidden)
    train = _graphs(cfg, cfg.train_seeds)
    val = _graphs(cfg, cfg.val_seeds)
    feats = [pair_features(g.T_init, g.pairs, g.stats) for g in train]
    metrics: dict[str, Any] = {"train_graphs": len(train), "val_graphs": len(val)}
    metrics["val_unit"] = evaluate_pairnet(None, val, cfg.eval_iterations)
    metrics["val_cauchy_rms_m"] = _robust_rms(val, "cauchy", 0.05, cfg.eval_iterations)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    history = []
    for step in range(cfg.steps + 1):
        if step % cfg.eval_every == 0 or step == cfg.steps:
            ev = evaluate_pairnet(net, val, cfg.eval_iterations)
            monitor.scalars(ev, step, prefix="val/")
            history.append({"step": step, **{f"val/{k}": x for k, x in ev.items()}})
        if step == cfg.steps:
            metrics["val_learned"] = ev  # the last evaluation is of the trained network
            break
        idx = list(range(len(train)))
        if 0 < cfg.batch_size < len(train):
            idx = torch.randperm(len(train), generator=gen)[: cfg.batch_size].tolist()
        graphs = [train[i] for i in idx]
        weights = [net(feats[i]) for i in idx]
        T = weighted_optimize(graphs, weights, cfg.unroll)
        loss = sum(pose_error(t, g.T_gt) for t, g in zip(T, graphs)) / len(graphs)
        opt.zero_grad()
        loss.backward()
        opt.step()
        w = torch.cat([x.detach() for x in weights])
        false = torch.cat([g.false for g in graphs])
        monitor.scalars({"loss": float(loss.detach()), "weight_false": float(w[false].mean()), "weight_true": float(w[~false].mean())},
                        step, prefix="train/")
        if step == 0:
            metrics["train_loss_first"] = float(loss.detach())
        metrics["train_loss_last"] = float(loss.detach())
    metrics["train_rms_unit_m"] = evaluate_pairnet(None, train, cfg.eval_iterations)["rms_m"]
    metrics["train_rms_learned_m"] = evaluate_pairnet(net, train, cfg.eval_iterations)["rms_m"]
    monitor.hparams({"hidden": cfg.hidden, "unroll": cfg.unroll, "lr": cfg.lr},
                    {"val_rms_m": metrics["val_learned"]["rms_m"], "val_weight_false": metrics["val_learned"]["weight_false"]})
    return TrainResult(net, metrics, history)
