"""Batched SO(3)/SE(3) geometry, quaternions, the pinhole camera and rigid alignment."""

from .align import umeyama_alignment
from .camera import (
    PinholeCamera,
    backproject_depth,
    distort_normalized,
    intrinsics_matrix,
    project_points,
    scale_intrinsics,
    undistort_pixels,
    undistorted_rays,
)
from .lie import (
    SMALL_ANGLE,
    se3_act,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_exp_numpy,
    se3_from_Rt,
    se3_inverse,
    se3_log,
    skew,
    so3_angle,
    so3_exp,
    so3_log,
    vex,
)
from .quaternion import quat_xyzw_slerp, quat_xyzw_to_rotmat, rotmat_to_quat_xyzw

__all__ = [
    "PinholeCamera",
    "SMALL_ANGLE",
    "backproject_depth",
    "distort_normalized",
    "intrinsics_matrix",
    "project_points",
    "quat_xyzw_slerp",
    "quat_xyzw_to_rotmat",
    "rotmat_to_quat_xyzw",
    "scale_intrinsics",
    "se3_act",
    "se3_adjoint",
    "se3_compose",
    "se3_exp",
    "se3_exp_numpy",
    "se3_from_Rt",
    "se3_inverse",
    "se3_log",
    "skew",
    "so3_angle",
    "so3_exp",
    "so3_log",
    "umeyama_alignment",
    "undistort_pixels",
    "undistorted_rays",
    "vex",
]
