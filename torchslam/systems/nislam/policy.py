"""NI-SLAM's keyframe rule: when a frame is fused, starts a keyframe, is matched again or is placed by prediction.

The rule, NI-SLAM §8 with two additions beyond the paper, reads one frame's match against its
keyframe (PSR, whether any pixels were well matched, its position) and the constant-velocity
prediction of its position:

- **lost**: PSR < ``T_K``, or no well-matched depth, or a *jump*: the position departs from the
  prediction by more than ``max_jump_m`` (a false correlation peak can score just above
  ``T_K`` while the true peak fades).
- A lost frame is matched again (``RETRY``) against a keyframe made from the last well-tracked
  frame, if there is one since the current keyframe was made.
- A frame still lost (or lost with no such frame) starts a keyframe of its own
  (``NEW_KEYFRAME``); its position is the prediction where it jumped, or, with
  ``lost_uses_prior``, wherever a prediction exists, unless the frame's depth matched and its
  own position lies within ``lost_agree_m`` of the prediction.
- A frame not lost keeps its keyframe (``TRACKED``) and is fused into it when PSR > ``T_M``.

The thresholds are read from ``NISlamConfig`` (``kcc.T_K``, ``kcc.T_M``, ``max_jump_m``,
``lost_uses_prior``, ``lost_agree_m``) into ``KeyframePolicy``, the one place that applies them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from torch import Tensor

from .config import NISlamConfig

__all__ = ["Action", "KeyframePolicy", "Verdict"]


class Action(enum.Enum):
    """What a frame's match leads to."""

    TRACKED = "tracked"  # the frame keeps its keyframe (and may be fused into it)
    RETRY = "retry"  # the last well-tracked frame becomes the keyframe; the frame is matched again
    NEW_KEYFRAME = "new_keyframe"  # the frame starts a keyframe of its own


@dataclass(frozen=True)
class Verdict:
    """The policy's decision on one match.

    Attributes:
        action: see ``Action``.
        fuse: fuse the frame into its keyframe (only with ``Action.TRACKED``).
        use_prior: the frame's position is the constant-velocity prediction, not its own
            correlation estimate (only with ``Action.NEW_KEYFRAME``).
    """

    action: Action
    fuse: bool = False
    use_prior: bool = False


@dataclass(frozen=True)
class KeyframePolicy:
    """The keyframe / fusion / lost rule (see the module docstring) with its thresholds.

    Attributes:
        T_K: PSR below which a match is lost (NI-SLAM Eq. (22)).
        T_M: PSR above which a tracked frame is fused into its keyframe (§8).
        max_jump_m: largest plausible distance from the predicted position, metres (``inf``: off),
            for a match at most ``T_M`` (one that would not be fused).
        lost_uses_prior: a frame lost even against a fresh keyframe takes the prediction as its position.
        lost_agree_m: ... unless its depth matched and its own position lies within this of the
            prediction, metres (0: never).
    """

    T_K: float
    T_M: float
    max_jump_m: float
    lost_uses_prior: bool
    lost_agree_m: float

    @classmethod
    def of(cls, cfg: NISlamConfig) -> KeyframePolicy:
        """The policy of ``cfg``."""
        return cls(
            T_K=cfg.kcc.T_K, T_M=cfg.kcc.T_M, max_jump_m=cfg.max_jump_m,
            lost_uses_prior=cfg.lost_uses_prior, lost_agree_m=cfg.lost_agree_m,
        )

    def decide(
        self, psr: float, depth_ok: bool, position: Tensor, predicted: Tensor | None, can_retry: bool, check_jump: bool = True
    ) -> Verdict:
        """Decide on one match.

        Args:
            psr: the match's peak-to-sidelobe ratio.
            depth_ok: some pixels were well matched (``TrackResult.depth_ok``).
            position: (3,) float64 the frame's position from the match, metres.
            predicted: (3,) float64 constant-velocity prediction of it, or None before two frames.
            can_retry: a well-tracked frame since the current keyframe can become the keyframe.
            check_jump: test ``position`` against ``predicted`` (``max_jump_m``). False where the
                prediction rests on a frame placed on the prediction itself: then every later
                frame that moves otherwise than that stale velocity would count as a jump, be
                placed on the prediction again, and tracking would never return.

        Returns:
            Verdict.
        """
        # A match confident enough to be fused is trusted over the prediction: the jump test is
        # for false peaks that score just above T_K while the true one fades.
        off = None if predicted is None else float((position - predicted).norm())  # metres from the prediction
        jump = check_jump and psr <= self.T_M and off is not None and off > self.max_jump_m
        if not (psr < self.T_K or not depth_ok or jump):
            return Verdict(Action.TRACKED, fuse=psr > self.T_M)
        if can_retry:
            return Verdict(Action.RETRY)
        prior = self.lost_uses_prior and off is not None
        if prior and depth_ok and off < self.lost_agree_m:
            prior = False  # the match agrees with the prediction: its own estimate is the finer one
        return Verdict(Action.NEW_KEYFRAME, use_prior=jump or prior)
