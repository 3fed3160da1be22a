"""Synthetic RGB-D-inertial sequences: a procedurally textured room rendered by batched ray casting.

``scene`` builds the room, ``render`` ray-casts it, ``motion`` holds the analytic trajectories
and ``sequence`` the settings, the lazily rendered sequence (with its simulated IMU and
attitude) and the TUM folder writer.
"""

from .motion import SYNTHETIC_TRAJECTORIES, SyntheticTrajectory, trajectory_kinematics, trajectory_pose
from .render import RenderOutput, SceneRenderer, kinect_depth_noise
from .scene import ROOM_CENTER, ROOM_HALF, Scene, build_scene
from .sequence import (
    TUM_FOLDER_ENTRIES,
    SyntheticConfig,
    SyntheticSequence,
    camera_from_config,
    generate_sequence,
    synthetic_kinematics,
    synthetic_trajectory,
    write_tum_folder,
)

__all__ = [
    "ROOM_CENTER",
    "ROOM_HALF",
    "SYNTHETIC_TRAJECTORIES",
    "TUM_FOLDER_ENTRIES",
    "RenderOutput",
    "Scene",
    "SceneRenderer",
    "SyntheticConfig",
    "SyntheticSequence",
    "SyntheticTrajectory",
    "build_scene",
    "camera_from_config",
    "generate_sequence",
    "kinect_depth_noise",
    "synthetic_kinematics",
    "synthetic_trajectory",
    "trajectory_kinematics",
    "trajectory_pose",
    "write_tum_folder",
]
