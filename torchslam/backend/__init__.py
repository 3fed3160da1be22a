"""Back-end optimisation shared by the systems: the SE(3) pose graph."""

from .posegraph import PoseGraphResult, edge_residuals, linearize_pose_graph, optimize_pose_graph

__all__ = ["PoseGraphResult", "edge_residuals", "linearize_pose_graph", "optimize_pose_graph"]
