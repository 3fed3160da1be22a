"""Learnable parameters: the config-value hook, training objectives, training loops and checkpoints.

``learnable(cfg, ["kcc.sigma", "kcc.lam", "kcc.temperature"])`` holds named config values as
``nn.Parameter``s; :mod:`~torchslam.learn.kcc` is the differentiable NI-SLAM front-end objective
(soft arg-max translation of keyframe/frame pairs), :mod:`~torchslam.learn.features` the
learned KCC channels trained through it, :mod:`~torchslam.learn.pairnet` the FastGO
per-pair weight network trained through unrolled iterations, :mod:`~torchslam.learn.train` the
loops that fit them, and ``save_checkpoint`` / ``load_checkpoint`` store them as plain data that
``torchslam run --params`` applies.
"""

from .features import (
    FeatureLoss,
    FeatureTrainConfig,
    OrthoPairs,
    evaluate_features,
    feature_loss,
    synthetic_ortho_pairs,
    train_features,
)
from .kcc import (
    KCCLoss,
    KCCPairs,
    content_translation,
    kcc_pair_errors,
    kcc_pairs_from_points,
    kcc_shift_loss,
    resized_kcc_config,
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
    "FeatureLoss",
    "FeatureTrainConfig",
    "KCCLoss",
    "KCCPairs",
    "KCCTrainConfig",
    "LearnableParams",
    "OrthoPairs",
    "PairNetTrainConfig",
    "PairWeightNet",
    "TrainResult",
    "checkpoint_values",
    "content_translation",
    "evaluate_features",
    "evaluate_kcc",
    "evaluate_pairnet",
    "false_loop_problem",
    "feature_loss",
    "kcc_pair_errors",
    "kcc_pairs_from_points",
    "kcc_shift_loss",
    "learnable",
    "load_checkpoint",
    "pair_features",
    "pose_error",
    "resized_kcc_config",
    "rms_translation_error",
    "save_checkpoint",
    "synthetic_kcc_pairs",
    "synthetic_ortho_pairs",
    "train_features",
    "train_kcc",
    "train_pairnet",
    "tum_kcc_pairs",
    "weighted_optimize",
]
