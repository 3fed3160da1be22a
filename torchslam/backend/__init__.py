"""Back-end optimisation shared by the systems: the SE(3) pose graph and its edge consistency test."""

from .posegraph import (
    EdgeTest,
    PoseGraphResult,
    chi2_quantile,
    edge_consistency,
    edge_residuals,
    graph_cost,
    linearize_pose_graph,
    optimize_pose_graph,
)

__all__ = [
    "EdgeTest", "PoseGraphResult", "chi2_quantile", "edge_consistency", "edge_residuals", "graph_cost",
    "linearize_pose_graph", "optimize_pose_graph",
]
