"""slamkit.geometry: camera models, SO3/SE3/Sim3 (float64), point-set alignment and two-view geometry.

Frames and units follow docs/conventions.md: ``T_a_b`` maps frame-b points to frame a, tangent vectors
are [omega, v] (SE3) and [omega, v, lambda = log s] (Sim3), metres/radians/pixels.
"""

from slamkit.geometry.alignment import horn_alignment, umeyama_alignment
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera, camera_from_config
from slamkit.geometry.se3 import SE3, invert_T, transform_points
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.so3 import (
    hat,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
    vee,
)
from slamkit.geometry.twoview import (
    cheirality_mask,
    parallax_deg,
    reprojection_error_px,
    triangulate_points,
    triangulate_rays,
)

__all__ = [
    "SE3",
    "KannalaBrandtCamera",
    "PinholeCamera",
    "Sim3",
    "camera_from_config",
    "cheirality_mask",
    "hat",
    "horn_alignment",
    "invert_T",
    "matrix_to_quat_xyzw",
    "parallax_deg",
    "quat_xyzw_to_matrix",
    "reprojection_error_px",
    "so3_exp",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_log",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "transform_points",
    "triangulate_points",
    "triangulate_rays",
    "umeyama_alignment",
    "vee",
]
