"""Training the learned KCC channels (``kcc.features=learned``) through the correlator, on synthetic data only.

Data. Keyframe/frame pairs rendered from synthetic sequences (``synthetic_ortho_pairs``), one
scene per seed, with the variety a real camera shows: the four trajectory kinds, the texture
density, the Kinect-like depth noise and the fraction of depth holes all drawn per seed, and a
grey gain, offset and noise drawn per frame. The pairs keep the orthographic images
(``OrthoPairs``), not channels: the channels are what is learned. The real sequences never
enter training, so they are a fair test of transfer.

Objective (``feature_loss``), per pair, through the differentiable KCC of NI-SLAM Eq. (11),
(17), (18):

    e = (t_xy - t_xy_true) / r_k                                     (pixels of the keyframe image)
    loss = mean(c^2 log(1 + |e|^2 / c^2)) + psr_weight * mean((log PSR - log PSR_handcrafted)^2)

``t_xy`` is the shift a run measures (``peak="refined"``: the integer peak refined by Newton
iterations on the Fourier interpolant, differentiable through those iterations) or the soft
arg-max of the response (``peak="soft"``). Both were measured (``FeatureTrainConfig.peak``): the
soft arg-max, a weighted mean over the whole response, barely moved the hard peak's error, so
training scores the refined peak by default.

The shift term is the squared error for errors well under ``c`` (``robust_px``, 1 px) and grows
only logarithmically beyond: a pair matched to a wrong peak tens of pixels away (a few per cent
of the pairs) would otherwise dominate every gradient.

The second, PSR-shaped term keeps each pair's peak-to-sidelobe ratio near the one the
hand-crafted channels give it, so the keyframe and fusion thresholds (``T_K``, ``T_M``) keep
their meaning with learned channels. σ, λ and the temperature stay at the config's values.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, ShapeError
from ..kcc import (
    FeatureKind,
    KCCConfig,
    KCCFeatureNet,
    KernelCorrelator,
    OrthoImages,
    kcc_predict,
    rgbd_to_points,
)
from ..systems.monitor import Monitor
from ..systems.nislam import NISlamConfig
from .kcc import TRAJECTORIES, _check_gaps, _pair_indices, ortho_pairs_from_points, resized_kcc_config
from .train import TrainResult, _check_training

__all__ = [
    "FeatureLoss",
    "FeatureTrainConfig",
    "OrthoPairs",
    "evaluate_features",
    "feature_loss",
    "synthetic_ortho_pairs",
    "train_features",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class OrthoPairs:
    """Keyframe/frame pairs as orthographic images, with ground truth.

    Attributes:
        keyframe: the keyframes' orthographic images, (B, H, W) fields.
        frame: the frames' images in the keyframes' attitude, at their resolution.
        resolution: (B,) keyframe resolutions ``r_k``, metres per pixel.
        t_xy: (B, 2) true image-plane content translation, metres.
    """

    keyframe: OrthoImages
    frame: OrthoImages
    resolution: Tensor
    t_xy: Tensor

    def __post_init__(self) -> None:
        B = self.resolution.shape[0]
        for name, img in (("keyframe", self.keyframe), ("frame", self.frame)):
            if img.grey.shape[0] != B or img.depth.shape != img.grey.shape or img.valid.shape != img.grey.shape:
                raise ShapeError(f"{name}: expected (B={B}, H, W) grey, depth and valid, got {tuple(img.grey.shape)}, "
                                 f"{tuple(img.depth.shape)}, {tuple(img.valid.shape)}")
        if self.t_xy.shape != (B, 2):
            raise ShapeError(f"t_xy: expected ({B}, 2), got {tuple(self.t_xy.shape)}")

    def __len__(self) -> int:
        return self.resolution.shape[0]

    def select(self, index: Tensor | slice) -> "OrthoPairs":
        """The pairs at ``index`` (a slice or (K,) int64 indices)."""
        return OrthoPairs(_select(self.keyframe, index), _select(self.frame, index), self.resolution[index], self.t_xy[index])

    @staticmethod
    def cat(parts: Sequence["OrthoPairs"]) -> "OrthoPairs":
        """Concatenate pair sets of the same image size."""
        if not parts:
            raise ShapeError("parts: expected at least one OrthoPairs, got none")
        return OrthoPairs(
            _cat([p.keyframe for p in parts]), _cat([p.frame for p in parts]),
            torch.cat([p.resolution for p in parts]), torch.cat([p.t_xy for p in parts]),
        )


def _select(img: OrthoImages, index) -> OrthoImages:
    return OrthoImages(img.grey[index], img.depth[index], img.valid[index], img.resolution[index], img.center[index])


def _cat(imgs: Sequence[OrthoImages]) -> OrthoImages:
    return OrthoImages(*(torch.cat([getattr(i, f) for i in imgs]) for f in ("grey", "depth", "valid", "resolution", "center")))


def _seed_variety(seed: int) -> dict[str, Any]:
    """Scene settings drawn from ``seed``: texture density, depth noise and holes (log-uniform / uniform)."""
    g = torch.Generator().manual_seed(1_000_003 * int(seed) + 17)
    u = torch.rand(3, generator=g, dtype=torch.float64).tolist()
    return {
        "texture_density": float(math.exp(math.log(48.0) + u[0] * (math.log(320.0) - math.log(48.0)))),
        "depth_noise_k": 0.0006 + 0.0024 * u[1],
        "depth_holes": 0.06 * u[2],
    }


def _motion_blur(rgb: Tensor, seed: int, max_px: float) -> Tensor:
    """Blur each (B, 3, H, W) image along a line of random direction and length up to ``max_px``.

    Half the frames stay sharp; the others are the mean of 7 bilinear samples along the line
    (hand-held motion during the exposure). Drawn from ``seed``.
    """
    if max_px == 0:
        return rgb
    g = torch.Generator().manual_seed(int(seed))
    B, _, H, W = rgb.shape
    length = max_px * torch.rand(B, generator=g) * (torch.rand(B, generator=g) < 0.5)
    angle = 2 * torch.pi * torch.rand(B, generator=g)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, H), torch.linspace(-1, 1, W), indexing="ij")
    base = torch.stack([xs, ys], dim=-1)[None].to(rgb.dtype)  # (1, H, W, 2) normalised x, y
    out = torch.zeros_like(rgb)
    for a in torch.linspace(-0.5, 0.5, 7).tolist():  # 7 taps of the line, not pixels
        d = torch.stack([torch.cos(angle) * 2 / W, torch.sin(angle) * 2 / H], dim=-1) * (a * length)[:, None]
        out += F.grid_sample(rgb, base + d[:, None, None].to(rgb.dtype), align_corners=True, padding_mode="border")
    return out / 7


def _photometric(grey: Tensor, seed: int, strength: float) -> Tensor:
    """Grey with a per-frame gain, offset and pixel noise drawn from ``seed`` (clamped to [0, 1])."""
    if strength == 0:
        return grey
    g = torch.Generator().manual_seed(int(seed))
    B = grey.shape[0]
    gain = 1 + strength * (2 * torch.rand(B, 1, generator=g) - 1)
    offset = 0.5 * strength * (2 * torch.rand(B, 1, generator=g) - 1)
    noise = 0.05 * strength * torch.randn(grey.shape, generator=g)
    return (grey * gain.to(grey.dtype) + offset.to(grey.dtype) + noise.to(grey.dtype)).clamp(0, 1)


def synthetic_ortho_pairs(
    seeds: Sequence[int],
    cfg: KCCConfig,
    frames: int = 60,
    keyframe_step: int = 5,
    gaps: Sequence[int] = (2, 5, 9, 14),
    width: int = 640,
    height: int = 480,
    photometric: float = 0.2,
    blur_px: float = 6.0,
    trajectories: Sequence[str] = TRAJECTORIES,
) -> OrthoPairs:
    """Render keyframe/frame pairs of synthetic sequences as orthographic images (see the module docstring).

    Sequence ``seed`` moves along ``trajectories[seed % len(trajectories)]`` through a scene
    whose texture density, depth noise and holes are drawn from the seed; its keyframes are
    frames ``0, keyframe_step, ...`` and the frame of keyframe ``n`` is ``gaps[n % len(gaps)]``
    frames later. Everything is a function of the seeds: the same seeds give the same pairs.

    Args:
        seeds: sequence seeds (training and validation use disjoint ones).
        cfg: orthographic size, coverage and sampling.
        frames: frames per sequence (at 30 Hz).
        keyframe_step: frames between keyframes.
        gaps: frame steps from a keyframe to its frame.
        width: rendered width, pixels.
        height: rendered height, pixels.
        photometric: strength of the per-frame grey gain (±strength), offset (±strength/2) and
            noise (σ = strength/20); 0 turns it off.
        blur_px: longest motion blur of a frame's colour image, pixels (half the frames are
            blurred, by up to this length; 0 turns it off).
        trajectories: trajectory kinds to cycle over.

    Returns:
        OrthoPairs in float32.
    """
    from ..data.synthetic import SyntheticConfig, generate_sequence

    gaps = _check_gaps(gaps, keyframe_step)
    if not seeds:
        raise ConfigError("seeds: expected at least one sequence seed, got none")
    if not 0 <= photometric < 1:
        raise ConfigError(f"photometric: expected a strength in [0, 1), got {photometric!r}")
    if not 0 <= blur_px <= 50:
        raise ConfigError(f"blur_px: expected a blur length in [0, 50] pixels, got {blur_px!r}")
    parts = []
    for seed in seeds:  # one scene per seed: data set-up, not a hot path
        scfg = SyntheticConfig(frames=frames, width=width, height=height, seed=int(seed),
                               trajectory=trajectories[int(seed) % len(trajectories)], **_seed_variety(int(seed)))
        seq = generate_sequence(scfg)
        starts, ends = _pair_indices(frames, keyframe_step, gaps)
        if not starts:
            raise ConfigError(f"gaps: no pair fits in {frames} frames with keyframe_step {keyframe_step} and gaps {list(gaps)}")
        rgb, depth = seq.render(starts + ends)
        rgb = _motion_blur(rgb, 104_729 * int(seed) + 3, blur_px)
        intr = seq.camera.as_tensor(torch.float32)
        points, grey, valid = rgbd_to_points(rgb, depth, intr)
        grey = _photometric(grey, 7919 * int(seed) + 1, photometric)
        B = len(starts)
        T = seq.groundtruth.T_wc
        kf, fr, t = ortho_pairs_from_points(points[:B], grey[:B], valid[:B], points[B:], grey[B:], valid[B:],
                                            T[starts], T[ends], cfg)
        parts.append(OrthoPairs(kf, fr, kf.resolution, t))
    return OrthoPairs.cat(parts)


def _correlator(cfg: KCCConfig, net: KCCFeatureNet | None) -> KernelCorrelator:
    """The run's correlator for ``cfg`` with ``net``'s channels (``None``: the hand-crafted ones)."""
    kind = FeatureKind.HANDCRAFTED if net is None else FeatureKind.LEARNED
    return KernelCorrelator(dataclasses.replace(cfg, features=kind), dtype=torch.float64, features=net)


def _correlate(pairs: OrthoPairs, cfg: KCCConfig, net: KCCFeatureNet | None, soft: tuple[bool, ...]):
    """KCC of the pairs, one prediction per entry of ``soft``: the soft arg-max shift (True) or the
    run's peak (False, ``cfg.subpixel`` refinement). Channels and filters are computed once."""
    corr = _correlator(cfg, net)
    x = corr.channels(pairs.frame, frame=True)  # tapered as in a run (``cfg.frame_taper``)
    filt = corr.fit(corr.channels(pairs.keyframe))
    return [
        kcc_predict(x, filt, cfg.sigma, pairs.resolution, psr_window=cfg.psr_window, temperature=cfg.temperature)
        if s else corr(x, filt, pairs.resolution)
        for s in soft
    ]


@dataclass(frozen=True)
class FeatureLoss:
    """The objective of a batch of pairs (see the module docstring).

    Attributes:
        loss: 0-d total, differentiable.
        shift_px2: 0-d mean robust squared soft arg-max error, pixels^2.
        psr_term: 0-d mean squared log-PSR difference to the hand-crafted channels.
        error_px: (B, 2) soft arg-max error, pixels.
        psr: (B,) PSR with the network's channels.
    """

    loss: Tensor
    shift_px2: Tensor
    psr_term: Tensor
    error_px: Tensor
    psr: Tensor


def feature_loss(
    net: KCCFeatureNet,
    pairs: OrthoPairs,
    cfg: KCCConfig,
    reference_psr: Tensor,
    psr_weight: float = 0.1,
    robust_px: float = 1.0,
    peak: str = "refined",
) -> FeatureLoss:
    """Robust shift error plus the PSR-shaped term, through the network and the correlator.

    Args:
        net: the learned channels.
        pairs: B pairs.
        cfg: σ, λ, temperature, PSR window, normalisation and hole filling of the hand-crafted part.
        reference_psr: (B,) PSR of the same pairs with the hand-crafted channels.
        psr_weight: weight of the PSR term.
        robust_px: scale ``c`` of the robust shift term, pixels.
        peak: ``"soft"``, the soft arg-max shift, or ``"refined"``, the shift a run measures
            (integer peak refined by ``cfg.subpixel``; differentiable through the Newton
            iterations of the Fourier refinement, not through the integer peak).

    Returns:
        FeatureLoss.
    """
    if not robust_px > 0:
        raise ConfigError(f"robust_px: expected a positive scale in pixels, got {robust_px!r}")
    if reference_psr.shape != (len(pairs),):
        raise ShapeError(f"reference_psr: expected ({len(pairs)},), got {tuple(reference_psr.shape)}")
    if peak not in ("soft", "refined"):
        raise ConfigError(f"peak: expected 'soft' or 'refined', got {peak!r}")
    (pred,) = _correlate(pairs, cfg, net, (peak == "soft",))
    err = (pred.t_xy - pairs.t_xy) / pairs.resolution[:, None]
    c2 = robust_px**2
    shift = (c2 * torch.log1p(err.square().sum(1) / c2)).mean()
    tiny = torch.finfo(pred.psr.dtype).tiny
    psr_term = (pred.psr.clamp_min(tiny).log() - reference_psr.clamp_min(tiny).log()).square().mean()
    return FeatureLoss(shift + psr_weight * psr_term, shift, psr_term, err, pred.psr)


def evaluate_features(pairs: OrthoPairs, cfg: KCCConfig, net: KCCFeatureNet | None, chunk: int = 16) -> dict[str, float]:
    """Validation figures of a network (``None``: the hand-crafted channels) on pairs, without gradients.

    Returns:
        ``score_px2`` (the mean squared error truncated at 2 px: accuracy and failures in one
        figure, what picks the checkpoint), ``rms_px``, ``median_px``, ``fail_rate`` (> 2 px) of
        the shift a plain run measures (hard peak with ``cfg.subpixel``), ``soft_rms_px`` of the
        soft arg-max, ``median_psr``.
    """
    errs, soft_errs, psrs = [], [], []
    with torch.no_grad():
        for a in range(0, len(pairs), chunk):
            part = pairs.select(slice(a, a + chunk))
            hard, soft = _correlate(part, cfg, net, (False, True))
            errs.append(((hard.t_xy - part.t_xy) / part.resolution[:, None]).norm(dim=1))
            soft_errs.append(((soft.t_xy - part.t_xy) / part.resolution[:, None]).norm(dim=1))
            psrs.append(hard.psr)
    e, s, p = torch.cat(errs).double(), torch.cat(soft_errs).double(), torch.cat(psrs).double()
    return {
        "score_px2": float(e.clamp_max(2).square().mean()),
        "rms_px": float(e.square().mean().sqrt()),
        "median_px": float(e.median()),
        "fail_rate": float((e > 2).double().mean()),
        "soft_rms_px": float(s.square().mean().sqrt()),
        "median_psr": float(p.median()),
    }


def _reference_psr(pairs: OrthoPairs, cfg: KCCConfig, chunk: int = 16) -> Tensor:
    with torch.no_grad():
        return torch.cat([_correlate(pairs.select(slice(a, a + chunk)), cfg, None, (True,))[0].psr
                          for a in range(0, len(pairs), chunk)])


@dataclass(frozen=True)
class FeatureTrainConfig:
    """Settings of :func:`train_features`.

    Attributes:
        learned: learned channels beside the two hand-crafted ones (``KCCFeatureNet``).
        hidden: hidden width of the network.
        train_seeds: synthetic sequence seeds to train on.
        val_seeds: held-out synthetic seeds to validate on (and to pick the checkpoint by).
        frames: frames per synthetic sequence.
        keyframe_step: frames between keyframes of the pairs.
        gaps: frame steps from a keyframe to its frame (cycled).
        width: rendered width, pixels.
        height: rendered height, pixels.
        ortho_height: orthographic image height (NI-SLAM's default, so the learned filters see
            the scale they will run at).
        ortho_width: orthographic image width.
        photometric: per-frame grey gain / offset / noise strength (``synthetic_ortho_pairs``).
        blur_px: longest motion blur of a frame, pixels (``synthetic_ortho_pairs``).
        initial_weight: starting share of each learned channel (``KCCFeatureNet``).
        steps: Adam steps.
        lr: Adam learning rate.
        batch_size: pairs per step.
        psr_weight: weight of the PSR-shaped term.
        robust_px: scale of the robust shift term, pixels (``feature_loss``).
        peak: the shift the objective scores (``feature_loss``): ``"refined"``, the run's own
            estimate (integer peak refined by ``subpixel``), or ``"soft"``, the soft arg-max.
            Measured on held-out seeds, 120 steps: refined took the median shift error from
            0.25 to 0.16-0.18 px, soft left it at 0.26 px.
        seed: seeds the network's initialisation and the mini-batch sampling.
        eval_every: validate every this many steps.
    """

    learned: int = 2
    hidden: int = 4
    # Seeds apart from the synthetic sequences benchmarks and tests run (0-4, 100-104, ...), so
    # that those stay unseen by the learned channels too.
    train_seeds: tuple[int, ...] = tuple(range(1000, 1016))
    val_seeds: tuple[int, ...] = (1100, 1101, 1102, 1103)
    frames: int = 90
    keyframe_step: int = 5
    gaps: tuple[int, ...] = (3, 8, 14, 20, 28)
    width: int = 640
    height: int = 480
    ortho_height: int = 360
    ortho_width: int = 480
    photometric: float = 0.2
    blur_px: float = 6.0
    initial_weight: float = 0.3
    steps: int = 600
    lr: float = 0.003
    batch_size: int = 6
    psr_weight: float = 0.1
    robust_px: float = 1.0
    peak: str = "refined"
    seed: int = 0
    eval_every: int = 50

    LIMITS: ClassVar[dict[str, Limit]] = {
        "learned": Limit(ge=1, le=6), "hidden": Limit(ge=1, le=64), "train_seeds": Limit(), "val_seeds": Limit(),
        "frames": AT_LEAST_1, "keyframe_step": AT_LEAST_1, "gaps": AT_LEAST_1, "width": AT_LEAST_1, "height": AT_LEAST_1,
        "ortho_height": AT_LEAST_1, "ortho_width": AT_LEAST_1, "photometric": Limit(ge=0, lt=1), "blur_px": Limit(ge=0, le=50),
        "initial_weight": POSITIVE, "steps": AT_LEAST_1,
        "lr": POSITIVE, "batch_size": AT_LEAST_1, "psr_weight": NON_NEGATIVE, "robust_px": POSITIVE, "seed": Limit(), "eval_every": AT_LEAST_1,
    }

    def __post_init__(self) -> None:
        _check_training(self)
        if self.peak not in ("soft", "refined"):
            raise ConfigError(f"peak: expected 'soft' or 'refined', got {self.peak!r}")


def train_features(cfg: FeatureTrainConfig | None = None, base: NISlamConfig | None = None,
                   monitor: Monitor | None = None):
    """Train the learned KCC channels on synthetic pairs (see the module docstring).

    Adam on the network's weights; every ``eval_every`` steps the hard-peak shift error on the
    validation seeds is measured, and the weights with the lowest validation ``score_px2`` are
    the result (a function of the seeds alone, not of any real sequence).

    Args:
        cfg: training settings.
        base: the NI-SLAM config whose KCC settings (σ, λ, temperature, normalisation) are used.
        monitor: where scalars go (TensorBoard in ``scripts/train.py``).

    Returns:
        TrainResult with the ``KCCFeatureNet``, metrics (``val_handcrafted``,
        ``val_learned``, ``train_handcrafted``, ``parameters``, ``best_step``...) and history.
    """
    cfg = cfg or FeatureTrainConfig()
    base = base or NISlamConfig()
    monitor = monitor or Monitor()
    kcc_cfg = resized_kcc_config(base.kcc, cfg.ortho_height, cfg.ortho_width,
                                 features=FeatureKind.HANDCRAFTED, features_weights="")
    t0 = time.perf_counter()
    logger.info("rendering %d training and %d validation sequences", len(cfg.train_seeds), len(cfg.val_seeds))
    common = dict(frames=cfg.frames, keyframe_step=cfg.keyframe_step, gaps=cfg.gaps, width=cfg.width,
                  height=cfg.height, photometric=cfg.photometric, blur_px=cfg.blur_px)
    train = synthetic_ortho_pairs(cfg.train_seeds, kcc_cfg, **common)
    val = synthetic_ortho_pairs(cfg.val_seeds, kcc_cfg, **common)
    ref_psr = _reference_psr(train, kcc_cfg)
    data_s = time.perf_counter() - t0
    torch.manual_seed(cfg.seed)
    net = KCCFeatureNet(cfg.learned, cfg.hidden, cfg.initial_weight)
    params = sum(p.numel() for p in net.parameters())
    metrics: dict[str, Any] = {"train_pairs": len(train), "val_pairs": len(val), "parameters": params,
                               "architecture": net.architecture(), "data_seconds": data_s}
    metrics["val_handcrafted"] = evaluate_features(val, kcc_cfg, None)
    metrics["val_initial"] = evaluate_features(val, kcc_cfg, net)
    for k, v in metrics["val_handcrafted"].items():
        monitor.scalar(f"val_handcrafted/{k}", v, 0)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    history: list[dict[str, float]] = []
    best = (math.inf, 0, {k: v.detach().clone() for k, v in net.state_dict().items()})
    order = torch.empty(0, dtype=torch.int64)
    for step in range(cfg.steps + 1):
        if step % cfg.eval_every == 0 or step == cfg.steps:
            ev = evaluate_features(val, kcc_cfg, net)
            monitor.scalars(ev, step, prefix="val/")
            w = net.channel_weights().detach().tolist()
            monitor.scalars({f"c{c}": x for c, x in enumerate(w)}, step, prefix="channel_weight/")
            history.append({"step": step, **{f"val/{k}": x for k, x in ev.items()}})
            if ev["score_px2"] < best[0]:
                best = (ev["score_px2"], step, {k: v.detach().clone() for k, v in net.state_dict().items()})
            hc = metrics["val_handcrafted"]
            logger.info("step %d: val score %.4f px^2, median %.3f px, fails %.3f (hand-crafted %.4f, %.3f, %.3f)", step,
                        ev["score_px2"], ev["median_px"], ev["fail_rate"], hc["score_px2"], hc["median_px"], hc["fail_rate"])
        if step == cfg.steps:
            break
        if order.numel() < cfg.batch_size:  # epochs of a fixed shuffle: every pair seen alike
            order = torch.cat([order, torch.randperm(len(train), generator=gen)])
        idx, order = order[: cfg.batch_size], order[cfg.batch_size :]
        out = feature_loss(net, train.select(idx), kcc_cfg, ref_psr[idx], cfg.psr_weight, cfg.robust_px, cfg.peak)
        opt.zero_grad()
        out.loss.backward()
        opt.step()
        monitor.scalar("train/loss", float(out.loss.detach()), step)
        monitor.scalar("train/shift_px2", float(out.shift_px2.detach()), step)
        monitor.scalar("train/psr_term", float(out.psr_term.detach()), step)
        history.append({"step": step, "train/loss": float(out.loss.detach()), "train/shift_px2": float(out.shift_px2.detach())})
    net.load_state_dict(best[2])
    metrics["best_step"] = best[1]
    metrics["val_learned"] = evaluate_features(val, kcc_cfg, net)
    metrics["channel_weights"] = net.channel_weights().detach().tolist()
    metrics["seconds"] = time.perf_counter() - t0
    monitor.hparams({"learned": cfg.learned, "hidden": cfg.hidden, "lr": cfg.lr, "steps": cfg.steps, "peak": cfg.peak},
                    {"val_score_px2": metrics["val_learned"]["score_px2"],
                                                                           "val_median_px": metrics["val_learned"]["median_px"]})
    return TrainResult(net, metrics, history)

