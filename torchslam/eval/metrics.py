"""Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE).

Both metrics follow the definitions of the TUM RGB-D benchmark (Sturm et al., IROS 2012):

* ATE, Sturm Eq. (1)-(2): after associating the estimated and ground-truth poses by timestamp
  (by default evo's rule: nearest stamp within 0.01 s, :class:`Association`) and aligning the estimate onto the ground truth (Umeyama, rigid by default), the error of
  pose i is the distance between the aligned estimated camera centre and the true one,
  ``e_i = || s R p_est_i + t - p_gt_i ||`` in metres.
* RPE, Sturm Eq. (3)-(4): for a pair (i, j) of matched poses the relative error is
  ``E_ij = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` with ``G`` ground truth and ``P`` the (aligned)
  estimate; its translation error is ``|| trans(E_ij) ||`` (metres) and its rotation error the
  angle of ``rot(E_ij)`` (degrees).

Statistics are rmse, mean, median, population std, min, max and sse (sum of squares), so the
numbers agree with the ``evo`` package's ``APE``/``RPE`` with the translation part and the
rotation angle in degrees. Everything is computed in float64.

Convention:
    Poses are camera-to-world ``T_wc``. The alignment maps the estimate's world frame onto the
    ground truth's: an estimated pose ``[R_i | t_i]`` becomes ``[R_a R_i | s R_a t_i + t_a]``,
    where ``T_align = [R_a | t_a]`` is rigid and the scale ``s`` is kept apart (``s = 1``
    unless the alignment is Sim(3)).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum
from typing import Any

import torch
from torch import Tensor

from ..data.frame import associate_timestamps
from ..data.trajectory import Trajectory
from ..errors import ConfigError, ShapeError, TorchSlamError, check_shape, parse_choice
from ..geometry import se3_inverse, so3_angle, umeyama_alignment

__all__ = [
    "AlignMode",
    "ATEResult",
    "Association",
    "EVO_MAX_DT",
    "DeltaUnit",
    "EvaluationError",
    "RPEResult",
    "associate_trajectories",
    "ate",
    "error_statistics",
    "rpe",
    "rpe_pairs",
]

logger = logging.getLogger(__name__)

STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max", "sse")

EVO_MAX_DT = 0.01
"""evo's default association tolerance (``evo_ape --t_max_diff``), seconds: the default here."""


class EvaluationError(TorchSlamError, ValueError):
    """Two trajectories cannot be compared (no common timestamps, too few poses or pairs)."""


class AlignMode(str, Enum):
    """How the estimate is aligned onto the ground truth before the errors are measured."""

    SE3 = "se3"
    """Rigid alignment (rotation and translation), Umeyama without scale."""
    SIM3 = "sim3"
    """Similarity alignment (rotation, translation and one scale), for scale-free estimates."""
    NONE = "none"
    """No alignment: both trajectories are taken to share one world frame."""


class Association(str, Enum):
    """How estimated and ground-truth poses are paired by timestamp."""

    NEAREST = "nearest"
    """evo's ``nearest_time`` rule (``evo.core.sync.associate_trajectories``): every pose of the
    trajectory with fewer poses takes the nearest-in-time pose of the other within ``max_dt``;
    a pose of the longer one may serve twice."""
    UNIQUE = "unique"
    """The TUM benchmark's ``associate.py`` rule: candidate pairs within ``max_dt`` in order of
    increasing gap, each pose used at most once (:func:`torchslam.data.frame.associate_timestamps`)."""


class DeltaUnit(str, Enum):
    """What the RPE step ``delta`` counts."""

    FRAMES = "frames"
    """``delta`` matched poses apart."""
    SECONDS = "seconds"
    """At least ``delta`` seconds apart (ground-truth clock)."""


def _check_trajectory(traj: Any, name: str) -> None:
    if not isinstance(traj, Trajectory):
        raise ShapeError(f"{name}: expected a Trajectory, got {type(traj).__name__}")
    dims: dict[str, int] = {}
    check_shape(traj.timestamps, "N", f"{name}.timestamps", dims)
    check_shape(traj.T_wc, "N 4 4", f"{name}.T_wc", dims)
    if traj.timestamps.dtype != torch.float64:
        raise ShapeError(f"{name}.timestamps: expected float64, got {traj.timestamps.dtype}")


def _check_seconds(value: float, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected a number of seconds, got {value!r}") from None
    if not math.isfinite(value):
        raise ConfigError(f"{name}: must be finite, got {value}")
    return value


def error_statistics(errors: Tensor) -> dict[str, float]:
    """Summarise per-pose errors.

    Args:
        errors: (K,) non-negative errors, K >= 1 (any unit; float64 is used).

    Returns:
        ``{"rmse", "mean", "median", "std", "min", "max", "sse"}`` as Python floats. ``std`` is
        the population standard deviation, ``median`` averages the two middle values for even K,
        and ``sse`` is the sum of squared errors (unit squared).
    """
    check_shape(errors, "K", "errors")
    if errors.shape[0] == 0:
        raise EvaluationError("errors: need at least one error to summarise, got none")
    e = errors.detach().to(torch.float64)
    k = e.shape[0]
    sorted_e = e.sort().values
    median = 0.5 * (sorted_e[(k - 1) // 2] + sorted_e[k // 2])
    sq = e * e
    values = torch.stack(
        [sq.mean().sqrt(), e.mean(), median, e.std(correction=0), sorted_e[0], sorted_e[-1], sq.sum()]
    ).tolist()
    return dict(zip(STAT_KEYS, values))


def associate_trajectories(
    est: Trajectory,
    gt: Trajectory,
    max_dt: float = EVO_MAX_DT,
    offset: float = 0.0,
    association: Association | str = Association.NEAREST,
) -> tuple[Tensor, Tensor]:
    """Pair estimated and ground-truth poses by timestamp.

    ``offset`` is added to the estimate's timestamps before matching (``t_est + offset`` is
    compared with ``t_gt``), for an estimator whose clock is shifted. The default is evo's
    association (``"nearest"``, ``max_dt`` 0.01 s), so ATE and RPE equal ``evo_ape`` /
    ``evo_rpe`` on the same files; ``"unique"`` is the TUM benchmark's one-to-one rule.

    Args:
        est: estimated trajectory.
        gt: ground-truth trajectory.
        max_dt: largest accepted timestamp gap, seconds.
        offset: time added to the estimate's stamps, seconds.
        association: ``"nearest"`` (evo) or ``"unique"`` (TUM), or an :class:`Association`.

    Returns:
        est_index, gt_index: (K,) int64 indices (on the CPU) of matched poses, in increasing
        time order (``"nearest"`` may repeat an index of the trajectory with more poses).

    Raises:
        EvaluationError: when no pair matches; the message gives both stamp counts and spans
            and the closest gap found.
    """
    _check_trajectory(est, "est")
    _check_trajectory(gt, "gt")
    max_dt = _check_seconds(max_dt, "max_dt")
    offset = _check_seconds(offset, "offset")
    if max_dt < 0:
        raise ConfigError(f"max_dt: must be >= 0 seconds, got {max_dt}")
    rule = parse_choice(Association, association, "association")
    t_est = est.timestamps.detach().cpu() + offset
    t_gt = gt.timestamps.detach().cpu()
    if rule is Association.NEAREST:
        est_index, gt_index = _associate_nearest(est.timestamps.detach().cpu(), t_gt, max_dt, offset)
    else:
        est_index, gt_index = associate_timestamps(t_est, t_gt, max_gap=max_dt)
    if est_index.numel() == 0:
        raise EvaluationError(_no_match_message(t_est, t_gt, max_dt, offset))
    logger.debug("associated %d of %d estimated and %d ground-truth poses", est_index.numel(), len(est), len(gt))
    return est_index, gt_index


def _nearest_indices(t1: Tensor, t2: Tensor, max_dt: float) -> tuple[Tensor, Tensor]:
    """evo's ``matching_time_indices`` for sorted ``t2``: for each ``t1`` stamp its nearest ``t2``.

    The same float64 operations in the same order as evo 1.38 (insertion index ``side="right"``
    clamped to the last stamp; the later neighbour wins only when strictly nearer; stamps
    farther than ``max_dt`` outside ``t2``'s span are skipped), so every pair is evo's.
    """
    if t1.numel() == 0 or t2.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64)
        return empty, empty.clone()
    inside = (t1 >= t2[0] - max_dt) & (t1 <= t2[-1] + max_dt)
    hi = torch.searchsorted(t2, t1, right=True).clamp(max=t2.numel() - 1)
    diff_ub = t2[hi] - t1
    diff_lb = torch.where(hi > 0, t1 - t2[(hi - 1).clamp(min=0)], torch.full_like(t1, math.inf))
    take_ub = (diff_ub <= max_dt) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_dt) & (diff_lb <= diff_ub)
    keep = inside & (take_ub | take_lb)
    best = torch.where(take_ub, hi, hi - 1)
    return torch.nonzero(keep).flatten(), best[keep]


def _associate_nearest(t_est: Tensor, t_gt: Tensor, max_dt: float, offset: float) -> tuple[Tensor, Tensor]:
    """evo's ``associate_trajectories(gt, est, max_diff, offset_2=offset)`` as index pairs.

    evo starts from the trajectory with fewer poses (the estimate when both have as many) and
    adds the offset to the other one's stamps with the sign that keeps ``t_est + offset``
    against ``t_gt``.
    """
    if t_est.numel() > t_gt.numel():
        gt_index, est_index = _nearest_indices(t_gt, t_est + offset, max_dt)
    else:
        est_index, gt_index = _nearest_indices(t_est, t_gt + (-offset), max_dt)
    return est_index, gt_index


def _no_match_message(t_est: Tensor, t_gt: Tensor, max_dt: float, offset: float) -> str:
    def span(t: Tensor) -> str:
        return f"[{t[0].item():.6f}, {t[-1].item():.6f}] s" if t.numel() else "(empty)"

    msg = (
        f"no timestamps match within max_dt={max_dt} s (offset={offset} s): est has {t_est.numel()} stamps "
        f"{span(t_est)}, gt has {t_gt.numel()} stamps {span(t_gt)}"
    )
    if t_est.numel() and t_gt.numel():
        # Nearest ground-truth stamp of every estimated one: the neighbours around the insertion point.
        hi = torch.searchsorted(t_gt, t_est).clamp(max=t_gt.numel() - 1)
        lo = (hi - 1).clamp(min=0)
        gap = torch.minimum((t_gt[hi] - t_est).abs(), (t_gt[lo] - t_est).abs()).min().item()
        msg += f"; the closest gap is {gap:.6f} s"
    return msg


def _matched_poses(
    est: Trajectory, gt: Trajectory, max_dt: float, offset: float, association: Association | str
) -> tuple[Tensor, Tensor, Tensor]:
    est_index, gt_index = associate_trajectories(est, gt, max_dt, offset, association)
    device = est.T_wc.device
    T_est = est.T_wc.detach().to(torch.float64)[est_index.to(device)]
    T_gt = gt.T_wc.detach().to(device=device, dtype=torch.float64)[gt_index.to(device)]
    stamps = gt.timestamps.detach().to(device)[gt_index.to(device)]
    return T_est, T_gt, stamps


def _alignment(p_est: Tensor, p_gt: Tensor, mode: AlignMode) -> tuple[Tensor, Tensor]:
    """Return ``(T_align (4,4), scale ())`` mapping estimated positions onto ground truth."""
    k = p_est.shape[0]
    if mode is AlignMode.NONE:
        return torch.eye(4, dtype=p_est.dtype, device=p_est.device), p_est.new_ones(())
    if k < 3:
        raise EvaluationError(f"align={mode.value!r} needs at least 3 matched poses, got {k}")
    if mode is AlignMode.SIM3:
        spread = (p_est - p_est.mean(0)).square().sum(-1).mean()
        if not bool(spread > 0):
            raise EvaluationError("align='sim3': the estimated positions do not move, so no scale can be fitted")
    T, scale = umeyama_alignment(p_est[None], p_gt[None], with_scale=mode is AlignMode.SIM3)
    return T[0], scale[0]


def _apply_alignment(T_align: Tensor, scale: Tensor, T_wc: Tensor) -> Tensor:
    """Map poses ``(K,4,4)`` into the ground-truth frame: ``[R_a R | s R_a t + t_a]``."""
    out = T_wc.clone()
    R_a, t_a = T_align[:3, :3], T_align[:3, 3]
    out[:, :3, :3] = R_a @ T_wc[:, :3, :3]
    out[:, :3, 3] = scale * (T_wc[:, :3, 3] @ R_a.T) + t_a
    return out


@dataclass(frozen=True)
class ATEResult:
    """Absolute trajectory error of one estimate against its ground truth.

    Attributes:
        stats: rmse/mean/median/std/min/max in metres and sse in square metres.
        errors: (K,) float64 per-pose position errors after alignment, metres.
        timestamps: (K,) float64 ground-truth timestamps of the matched poses, seconds.
        align: the alignment mode used (``"se3"``, ``"sim3"`` or ``"none"``).
        T_align: (4, 4) float64 rigid part ``[R_a | t_a]`` of the alignment (identity for
            ``"none"``).
        scale: the alignment's scale (1.0 unless ``align == "sim3"``).
        matched: number K of associated pose pairs.
        association: the association rule (``"nearest"`` or ``"unique"``).
        max_dt: the association tolerance, seconds.
    """

    stats: dict[str, float]
    errors: Tensor
    timestamps: Tensor
    align: str
    T_align: Tensor
    scale: float
    matched: int
    association: str = Association.NEAREST.value
    max_dt: float = EVO_MAX_DT

    def to_dict(self, with_errors: bool = False) -> dict[str, Any]:
        """Return a JSON-ready dict (statistics in metres; per-pose errors only if asked)."""
        out: dict[str, Any] = {
            "metric": "ate",
            "align": self.align,
            "association": self.association,
            "max_dt_s": self.max_dt,
            "matched": self.matched,
            "scale": self.scale,
            "T_align": self.T_align.tolist(),
            "unit": "m",
            "stats": dict(self.stats),
        }
        if with_errors:
            out["errors"] = self.errors.tolist()
        return out


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error of one estimate against its ground truth.

    Attributes:
        trans_stats: statistics of the translation errors, metres (sse in square metres).
        rot_stats: statistics of the rotation errors, degrees (sse in square degrees).
        trans_errors: (P,) float64 translation error per pair, metres.
        rot_errors: (P,) float64 rotation angle error per pair, degrees.
        pairs: (P, 2) int64 indices (i, j) of each pair into the matched poses.
        delta: the step between the two poses of a pair.
        unit: what ``delta`` counts (``"frames"`` or ``"seconds"``).
        all_pairs: whether every pose started a pair (True) or the pairs were chained (False).
        align: the alignment mode used.
        scale: the alignment's scale (only ``"sim3"`` changes RPE, by rescaling translations).
        matched: number of associated poses the pairs were drawn from.
    """

    trans_stats: dict[str, float]
    rot_stats: dict[str, float]
    trans_errors: Tensor
    rot_errors: Tensor
    pairs: Tensor
    delta: float
    unit: str
    all_pairs: bool
    align: str
    scale: float
    matched: int

    def to_dict(self, with_errors: bool = False) -> dict[str, Any]:
        """Return a JSON-ready dict (translation in metres, rotation in degrees)."""
        out: dict[str, Any] = {
            "metric": "rpe",
            "align": self.align,
            "delta": self.delta,
            "unit": self.unit,
            "all_pairs": self.all_pairs,
            "matched": self.matched,
            "pairs": int(self.pairs.shape[0]),
            "scale": self.scale,
            "trans_stats_m": dict(self.trans_stats),
            "rot_stats_deg": dict(self.rot_stats),
        }
        if with_errors:
            out["trans_errors_m"] = self.trans_errors.tolist()
            out["rot_errors_deg"] = self.rot_errors.tolist()
        return out


def ate(
    est: Trajectory,
    gt: Trajectory,
    align: AlignMode | str = AlignMode.SE3,
    max_dt: float = EVO_MAX_DT,
    offset: float = 0.0,
    association: Association | str = Association.NEAREST,
) -> ATEResult:
    """Compute the absolute trajectory error (Sturm et al. 2012, Eq. (1)-(2)).

    Poses are associated by timestamp (:func:`associate_trajectories`), the estimated camera
    centres are aligned onto the ground-truth ones by Umeyama's method (rigid for ``"se3"``,
    with scale for ``"sim3"``, not at all for ``"none"``), and the error of each pose is the
    distance between the aligned estimated centre and the true centre.

    Args:
        est: estimated trajectory (camera-to-world).
        gt: ground-truth trajectory (camera-to-world).
        align: ``"se3"`` (default), ``"sim3"`` or ``"none"``, or an :class:`AlignMode`.
        max_dt: largest timestamp gap accepted when associating, seconds (evo's 0.01 s).
        offset: time added to the estimate's stamps before associating, seconds.
        association: ``"nearest"`` (evo's rule, default) or ``"unique"``
            (:func:`associate_trajectories`).

    Returns:
        The :class:`ATEResult`, errors in metres. With the defaults it is what
        ``evo_ape tum gt est -a`` (``"se3"``) or ``-as`` (``"sim3"``) reports.

    Raises:
        ConfigError: unknown ``align`` or ``association`` (the message lists the valid ones) or
            bad ``max_dt``.
        ShapeError: an argument is not a well-formed Trajectory.
        EvaluationError: no common timestamps, or too few poses for the alignment.
    """
    mode = parse_choice(AlignMode, align, "align")
    T_est, T_gt, stamps = _matched_poses(est, gt, max_dt, offset, association)
    p_est, p_gt = T_est[:, :3, 3], T_gt[:, :3, 3]
    T_align, scale = _alignment(p_est, p_gt, mode)
    p_aligned = scale * (p_est @ T_align[:3, :3].T) + T_align[:3, 3]
    errors = (p_aligned - p_gt).norm(dim=-1)  # (K,)
    return ATEResult(
        stats=error_statistics(errors),
        errors=errors,
        timestamps=stamps,
        align=mode.value,
        T_align=T_align,
        scale=float(scale),
        matched=int(errors.shape[0]),
        association=parse_choice(Association, association, "association").value,
        max_dt=float(max_dt),
    )


def rpe_pairs(
    timestamps: Tensor, delta: float, unit: DeltaUnit | str = DeltaUnit.FRAMES, all_pairs: bool = False
) -> Tensor:
    """Choose the index pairs (i, j) over which the relative pose error is taken.

    * ``unit="frames"``: ``j = i + delta``. With ``all_pairs`` every ``i`` starts a pair;
      otherwise the pairs are chained, ``(0, d), (d, 2d), ...``.
    * ``unit="seconds"``: ``j`` is the first index after ``i`` with
      ``timestamps[j] - timestamps[i] >= delta``; poses with no such ``j`` start no pair. With
      ``all_pairs`` every ``i`` starts a pair; otherwise the pairs are chained from index 0,
      each starting where the previous one ended.

    Args:
        timestamps: (K,) float64 strictly increasing seconds (only used for ``"seconds"``).
        delta: positive integer number of frames, or positive number of seconds.
        unit: ``"frames"`` or ``"seconds"``, or a :class:`DeltaUnit`.
        all_pairs: one pair per starting pose instead of a chain of non-overlapping pairs.

    Returns:
        (P, 2) int64 pairs on the device of ``timestamps``, sorted by i.
    """
    check_shape(timestamps, "K", "timestamps")
    unit = parse_choice(DeltaUnit, unit, "unit")
    k = timestamps.shape[0]
    device = timestamps.device
    if unit is DeltaUnit.FRAMES:
        try:
            ok = not isinstance(delta, bool) and float(delta).is_integer() and int(delta) >= 1
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"delta: with unit='frames' expected a positive integer, got {delta!r}")
        d = int(delta)
        i = torch.arange(0, max(k - d, 0), 1 if all_pairs else d, device=device)
        return torch.stack([i, i + d], dim=-1)
    delta = _check_seconds(delta, "delta")
    if delta <= 0:
        raise ConfigError(f"delta: with unit='seconds' expected a positive duration, got {delta}")
    t = timestamps.to(torch.float64)
    idx = torch.arange(k, device=device)
    # First j > i with t[j] - t[i] >= delta: search for t[i] + delta, then correct the one-step
    # error that rounding t[i] + delta can cause, so the rule holds on the differences themselves.
    j = torch.maximum(torch.searchsorted(t, t + delta, side="left"), idx + 1)
    prev = (j - 1).clamp(min=0)
    j = torch.where((j - 1 > idx) & (t[prev] - t >= delta), j - 1, j)
    cur = j.clamp(max=max(k - 1, 0))
    j = torch.where((j < k) & (t[cur] - t < delta), j + 1, j)
    nxt = j.clamp(max=k)  # k = "no partner"
    if all_pairs:
        keep = nxt < k
    else:
        # Poses reachable from 0 by repeated nxt, by pointer doubling: after r rounds `reach`
        # holds nxt^m(0) for all m < 2^r, with k a sink that absorbs chains running off the end.
        jump = torch.cat([nxt, nxt.new_full((1,), k)])
        reach = torch.zeros(k + 1, dtype=torch.bool, device=device)
        reach[0] = k > 0
        for _ in range(max(k, 1).bit_length()):
            hit = torch.zeros_like(reach)
            hit[jump[reach]] = True
            reach = reach | hit
            jump = jump[jump]
        keep = reach[:k] & (nxt < k)
    return torch.stack([idx[keep], nxt[keep]], dim=-1)


def rpe(
    est: Trajectory,
    gt: Trajectory,
    delta: float = 1,
    unit: DeltaUnit | str = DeltaUnit.FRAMES,
    align: AlignMode | str = AlignMode.NONE,
    max_dt: float = EVO_MAX_DT,
    all_pairs: bool = False,
    offset: float = 0.0,
    association: Association | str = Association.NEAREST,
) -> RPEResult:
    """Compute the relative pose error (Sturm et al. 2012, Eq. (3)-(4)).

    Poses are associated by timestamp, pairs (i, j) of matched poses are chosen by
    :func:`rpe_pairs` (for ``unit="seconds"`` on the ground-truth stamps: j is the first pose at
    least ``delta`` seconds after i), and each pair gives
    ``E_ij = (G_i^-1 G_j)^-1 (P_i^-1 P_j)``. The translation error is ``||trans(E_ij)||`` in
    metres and the rotation error the angle of ``rot(E_ij)`` in degrees.

    A rigid alignment (``"se3"``) cancels in ``P_i^-1 P_j`` and leaves RPE unchanged, so the
    default is ``"none"``; ``"sim3"`` rescales the estimate's translations by the fitted scale
    first, which is what a scale-free (monocular) estimate needs.

    Args:
        est: estimated trajectory (camera-to-world).
        gt: ground-truth trajectory (camera-to-world).
        delta: step between the poses of a pair, in ``unit``.
        unit: ``"frames"`` (matched poses) or ``"seconds"``, or a :class:`DeltaUnit`.
        align: ``"none"`` (default), ``"se3"`` or ``"sim3"``, or an :class:`AlignMode`.
        max_dt: largest timestamp gap accepted when associating, seconds.
        all_pairs: one pair per starting pose instead of a chain of non-overlapping pairs.
        offset: time added to the estimate's stamps before associating, seconds.
        association: ``"nearest"`` (evo's rule, default) or ``"unique"``.

    Returns:
        The :class:`RPEResult`.

    Raises:
        ConfigError: unknown ``align`` or ``unit`` (listing the valid ones) or a bad ``delta``.
        ShapeError: an argument is not a well-formed Trajectory.
        EvaluationError: no common timestamps, or no pair ``delta`` apart.
    """
    mode = parse_choice(AlignMode, align, "align")
    unit = parse_choice(DeltaUnit, unit, "unit")
    T_est, T_gt, stamps = _matched_poses(est, gt, max_dt, offset, association)
    pairs = rpe_pairs(stamps, delta, unit, all_pairs)
    k = T_est.shape[0]
    if pairs.shape[0] == 0:
        span = (stamps[-1] - stamps[0]).item()
        raise EvaluationError(
            f"delta: no pose pair is {delta} {unit.value} apart among the {k} matched poses (spanning {span:.6f} s)"
        )
    T_align, scale = _alignment(T_est[:, :3, 3], T_gt[:, :3, 3], mode)
    T_est = _apply_alignment(T_align, scale, T_est)
    i, j = pairs[:, 0], pairs[:, 1]
    rel_gt = se3_inverse(T_gt[i]) @ T_gt[j]  # (P, 4, 4)
    rel_est = se3_inverse(T_est[i]) @ T_est[j]
    E = se3_inverse(rel_gt) @ rel_est
    trans_errors = E[:, :3, 3].norm(dim=-1)
    rot_errors = torch.rad2deg(so3_angle(E[:, :3, :3]))
    return RPEResult(
        trans_stats=error_statistics(trans_errors),
        rot_stats=error_statistics(rot_errors),
        trans_errors=trans_errors,
        rot_errors=rot_errors,
        pairs=pairs,
        delta=int(delta) if unit is DeltaUnit.FRAMES else float(delta),
        unit=unit.value,
        all_pairs=bool(all_pairs),
        align=mode.value,
        scale=float(scale),
        matched=k,
    )
