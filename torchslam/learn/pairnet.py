"""FastGO per-pair weights from a small network on pair features.

FastGO's objective (FastGO Eq. (1)) sums the pairs' squared residuals; ``optimize(...,
pair_weights=w)`` scales each pair's statistics by ``w`` and is differentiable in ``w`` through
its unrolled Gauss-Newton / LM iterations. :class:`PairWeightNet` predicts ``w`` from features
that need nothing but a pair's statistics and the current poses (:func:`pair_features`), so it
can switch off a false loop pair (wrong correspondences that agree with a wrong relative pose)
before the optimiser bends the map to it. It is trained by unrolling a fixed number of
iterations on synthetic pose graphs with planted false pairs (:func:`false_loop_problem`) and
scoring the optimised poses against ground truth (:func:`pose_error`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..errors import ConfigError, ShapeError, check_shape
from ..fastgo import FastGOConfig, FastGOProblem, PairStats, optimize_batch, pair_cost
from ..fastgo.synthetic import loop_route_problem, make_correspondences
from ..geometry import se3_exp

__all__ = [
    "FEATURES",
    "FalseLoopProblem",
    "PairWeightNet",
    "false_loop_problem",
    "pair_features",
    "pose_error",
    "rms_translation_error",
    "weighted_optimize",
]

#: Names of the columns of :func:`pair_features`.
FEATURES = ("log_n", "log_rms", "log_eig_ratio", "log_gap")

# RMS residuals are taken relative to 1 cm; eigenvalue ratios are floored at 1e-12.
_RMS_SCALE = 0.01
_EIG_FLOOR = 1e-12


def pair_features(T_wc: Tensor, pairs: Tensor, stats: PairStats) -> Tensor:
    """Per-pair features for :class:`PairWeightNet`, from the statistics and the current poses.

    Columns (:data:`FEATURES`):

    * ``log_n``: log of the correspondence weight sum ``n``;
    * ``log_rms``: log of the RMS residual per correspondence at the poses ``T_wc``, relative to
      1 cm (FastGO Eq. (1) through ``pair_cost``): a false loop disagrees with the odometry;
    * ``log_eig_ratio``: log of the smallest over the largest eigenvalue of the centred point
      scatter, the smaller of frames i and j (flat or line-like point sets constrain little);
    * ``log_gap``: ``log(1 + |i - j|)``, the keyframe index distance (odometry pairs are 1).

    Args:
        T_wc: (N, 4, 4) float64 current keyframe poses, camera to world.
        pairs: (M, 2) int64 keyframe indices.
        stats: statistics of the M pairs.

    Returns:
        (M, 4) float64 features (no gradient: they depend on the data, not on the weights).
    """
    check_shape(T_wc, "N 4 4", "T_wc")
    check_shape(pairs, f"{len(stats)} 2", "pairs")
    with torch.no_grad():
        st = stats.to(dtype=torch.float64)
        n = st.n.clamp_min(1e-12)
        cost = pair_cost(T_wc.to(torch.float64), pairs, st)
        rms = (cost / n).sqrt()
        _, _, C_ii, _, C_jj = st.centred()
        ev = torch.linalg.eigvalsh(torch.stack([C_ii, C_jj], 1))  # (M, 2, 3) ascending
        ratio = (ev[..., 0].clamp_min(0) / ev[..., 2].clamp_min(_EIG_FLOOR)).amin(dim=1)
        gap = (pairs[:, 0] - pairs[:, 1]).abs().to(torch.float64)
        return torch.stack(
            [n.log(), (rms / _RMS_SCALE + 1e-6).log(), ratio.clamp_min(_EIG_FLOOR).log(), gap.log1p()], dim=1
        )


class PairWeightNet(nn.Module):
    """MLP from per-pair features to a pair weight in ``(0, max_weight)``.

    The last layer starts at zero, so an untrained net gives every pair weight
    ``max_weight / 2`` (1 by default: plain FastGO).

    Args:
        hidden: width of the two hidden layers.
        max_weight: upper bound of the weights (``max_weight * sigmoid``).
        in_features: number of feature columns (``len(FEATURES)``).
    """

    def __init__(self, hidden: int = 16, max_weight: float = 2.0, in_features: int = len(FEATURES)):
        super().__init__()
        if not (isinstance(hidden, int) and hidden >= 1):
            raise ConfigError(f"hidden: expected a positive int, got {hidden!r}")
        if not max_weight > 0:
            raise ConfigError(f"max_weight: expected a positive number, got {max_weight!r}")
        self.hidden = hidden
        self.max_weight = float(max_weight)
        self.in_features = in_features
        self.mlp = nn.Sequential(
            nn.Linear(in_features, hidden, dtype=torch.float64), nn.Tanh(),
            nn.Linear(hidden, hidden, dtype=torch.float64), nn.Tanh(),
            nn.Linear(hidden, 1, dtype=torch.float64),
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, features: Tensor) -> Tensor:
        """Map (M, F) features to (M,) weights in ``(0, max_weight)``."""
        check_shape(features, f"M {self.in_features}", "features")
        return self.max_weight * torch.sigmoid(self.mlp(features.to(torch.float64))[:, 0])

    def architecture(self) -> dict:
        """Return the constructor arguments (stored in checkpoints)."""
        return {"hidden": self.hidden, "max_weight": self.max_weight, "in_features": self.in_features}


@dataclass(frozen=True)
class FalseLoopProblem:
    """A pose graph with planted false loop pairs and ground truth.

    Attributes:
        T_gt: (N, 4, 4) float64 true poses.
        T_init: (N, 4, 4) drifted initial poses (``T_init[0] == T_gt[0]``, the gauge).
        pairs: (M, 2) int64 pairs; the last ``num_false`` are false.
        stats: statistics of the M pairs.
        false: (M,) bool, True for the planted false pairs.
    """

    T_gt: Tensor
    T_init: Tensor
    pairs: Tensor
    stats: PairStats
    false: Tensor


def false_loop_problem(
    seed: int,
    num_keyframes: int = 24,
    lap_length: int = 8,
    num_false: int = 3,
    noise: float = 0.01,
    correspondences: int = 32,
    false_offset: tuple[float, float] = (0.3, 0.8),
    false_angle: float = 0.3,
) -> FalseLoopProblem:
    """Build a repeated-route graph (``fastgo.synthetic.loop_route_problem``) plus false loops.

    Each false pair joins two random keyframes at least three apart with correspondences that
    agree with a wrong relative pose: keyframe j is displaced by a random translation of
    ``false_offset`` metres and a rotation of up to ``false_angle`` radians, as a place
    recognition mistake between similar-looking places would.

    Args:
        seed: seed of every random choice.
        num_keyframes: N.
        lap_length: keyframes per lap of the route.
        num_false: false pairs to plant.
        noise: correspondence noise, metres.
        correspondences: correspondences per pair.
        false_offset: range of the false translation, metres.
        false_angle: largest false rotation, radians.

    Returns:
        FalseLoopProblem.
    """
    if num_keyframes < 5:
        raise ConfigError(f"num_keyframes: expected >= 5, got {num_keyframes}")
    if num_false < 0:
        raise ConfigError(f"num_false: expected >= 0, got {num_false}")
    P = loop_route_problem(num_keyframes, lap_length=lap_length, loops_per_keyframe=1, noise=noise,
                           correspondences=correspondences, seed=seed)
    g = torch.Generator().manual_seed(10_000 + seed)
    dt = torch.float64
    N = num_keyframes
    i = torch.randint(0, N - 3, (num_false,), generator=g)
    j = i + 3 + (torch.rand(num_false, generator=g, dtype=dt) * (N - 3 - i).to(dt)).floor().to(torch.int64)
    j = j.clamp(max=N - 1)
    lo, hi = false_offset
    direction = torch.randn(num_false, 3, generator=g, dtype=dt)
    direction = direction / direction.norm(dim=1, keepdim=True)
    dist = lo + (hi - lo) * torch.rand(num_false, 1, generator=g, dtype=dt)
    axis = torch.randn(num_false, 3, generator=g, dtype=dt)
    axis = axis / axis.norm(dim=1, keepdim=True) * false_angle * torch.rand(num_false, 1, generator=g, dtype=dt)
    wrong = se3_exp(torch.cat([direction * dist, axis], dim=1)) @ P.T_gt[j]
    bad_pairs = torch.stack([i, j], dim=1)
    # Each false pair's correspondences follow its own wrong pose of j.
    li, lj = make_correspondences(torch.cat([P.T_gt, wrong]), torch.stack([i, N + torch.arange(num_false)], 1),
                                  correspondences, noise, g)
    pairs = torch.cat([P.pairs, bad_pairs])
    stats = PairStats.cat([P.stats, PairStats.from_padded(li, lj)])
    false = torch.cat([torch.zeros(P.pairs.shape[0], dtype=torch.bool), torch.ones(num_false, dtype=torch.bool)])
    return FalseLoopProblem(P.T_gt, P.T_init, pairs, stats, false)


def weighted_optimize(
    problems: Sequence[FalseLoopProblem],
    weights: Sequence[Tensor] | None,
    iterations: int,
    unrolled: bool = True,
) -> list[Tensor]:
    """Optimise several graphs in one batched FastGO call with the given pair weights.

    Args:
        problems: B graphs.
        weights: B tensors (M_b,) of pair weights (may require grad), or None for weight 1.
        iterations: LM iterations.
        unrolled: run exactly ``iterations`` steps (negative tolerances never stop early), so
            the gradient is that of a fixed unrolled computation; False stops at convergence.

    Returns:
        B tensors (N_b, 4, 4) of optimised poses.
    """
    if weights is not None and len(weights) != len(problems):
        raise ShapeError(f"weights: expected {len(problems)} tensors, got {len(weights)}")
    cfg = FastGOConfig(iterations=iterations, tol=-1.0 if unrolled else 1e-10, step_tol=-1.0 if unrolled else 1e-12)
    batch = [FastGOProblem(p.T_init, p.pairs, p.stats, 0, None if weights is None else weights[b])
             for b, p in enumerate(problems)]
    res = optimize_batch(batch, cfg)
    off = res.node_offsets.tolist()
    return [res.T_wc[off[b]:off[b + 1]] for b in range(len(problems))]


def pose_error(T_wc: Tensor, T_gt: Tensor) -> Tensor:
    """Mean squared pose error: ``|p - p_gt|² + |R - R_gt|_F² / 2`` averaged over keyframes.

    The rotation term is ``4 (1 - cos θ) ≈ 2 θ²`` / 2 = ``θ²`` for small angles θ, so 1 rad² counts
    like 1 m². Differentiable in ``T_wc``.

    Args:
        T_wc: (N, 4, 4) estimated poses.
        T_gt: (N, 4, 4) true poses in the same gauge.

    Returns:
        0-d float64.
    """
    d: dict[str, int] = {}
    check_shape(T_wc, "N 4 4", "T_wc", d)
    check_shape(T_gt, "N 4 4", "T_gt", d)
    dt = (T_wc[:, :3, 3] - T_gt[:, :3, 3]).square().sum(-1)
    dR = (T_wc[:, :3, :3] - T_gt[:, :3, :3]).square().sum((-1, -2)) / 2
    return (dt + dR).mean()


def rms_translation_error(T_wc: Tensor, T_gt: Tensor) -> float:
    """RMS keyframe position error in metres (a report figure, not differentiable)."""
    return math.sqrt(float((T_wc[:, :3, 3] - T_gt[:, :3, 3]).detach().square().sum(-1).mean()))
