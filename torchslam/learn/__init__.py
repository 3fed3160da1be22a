"""Learnable parameters: the config-value hook, training objectives, training loops and checkpoints.

``learnable(cfg, ["kcc.sigma", "kcc.lam", "kcc.temperature"])`` holds named config values as
``nn.Parameter``s; :mod:`~torchslam.learn.kcc` is the differentiable NI-SLAM front-end objective
(soft arg-max translation of keyframe/frame pairs), :mod:`~torchslam.learn.pairnet` the FastGO
per-pair weight network trained through unrolled iterations, :mod:`~torchslam.learn.train` the
loops that fit them, and ``save_checkpoint`` / ``load_checkpoint`` store them as plain data that
``torchslam run --params`` applies.
"""

from .kcc import (
    KCCLoss,
    KCCPairs,
    content_translation,
    kcc_pair_errors,
    kcc_pairs_from_points,
    kcc_shift_loss,
    synthetic_kcc_pairs,
    tum_kcc_pairs,
)
from .pairnet import (
    FEATURES,
    FalseLoopProblem,
    PairWeightNet,
    false_loop_problem,
    pair_features,
    pose_error,
    rms_translation_error,
    weighted_optimize,
)
from .params import LearnableParams, checkpoint_values, learnable, load_checkpoint, save_checkpoint
from .train import (
    KCCTrainConfig,
    PairNetTrainConfig,
    TrainResult,
    evaluate_kcc,
    evaluate_pairnet,
    train_kcc,
    train_pairnet,
)

__all__ = [
    "FEATURES",
    "FalseLoopProblem",
    "KCCLoss",
    "KCCPairs",
    "KCCTrainConfig",
    "LearnableParams",
    "PairNetTrainConfig",
    "PairWeightNet",
    "TrainResult",
    "checkpoint_values",
    "content_translation",
    "evaluate_kcc",
    "evaluate_pairnet",
    "false_loop_problem",
    "kcc_pair_errors",
    "kcc_pairs_from_points",
    "kcc_shift_loss",
    "learnable",
    "load_checkpoint",
    "pair_features",
    "pose_error",
    "rms_translation_error",
    "save_checkpoint",
    "synthetic_kcc_pairs",
    "train_kcc",
    "train_pairnet",
    "tum_kcc_pairs",
    "weighted_optimize",
]
