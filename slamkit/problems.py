"""Optimization problems and results: plain arrays in, plain arrays out.

An Optimizer never sees the map. The pipeline builds one of these problems from a snapshot of the map,
a backend solves it (possibly in another process: everything here pickles cheaply), and the pipeline
commits the result. Frames and units: ``T_c_w`` maps world points into the camera (ORB-SLAM's Tcw),
metres; ``S_c_w`` is the same with a scale (a Sim3 as a 4x4 matrix [[s R, t], [0, 1]]); pixels are px.

The camera model of pose and bundle problems is ``camera_model``: "pinhole" (the default) means observations are
keypoints of the ideal (undistorted) pinhole image, and intrinsics arrays ``(fx, fy, cx, cy)`` say everything
(ORB-SLAM2/3 undistort pinhole keypoints); "kannala_brandt" means observations are raw fisheye pixels, projected
with the same intrinsics and the equidistant model's ``distortion`` k1..k4 (ORB-SLAM3's KannalaBrandt8):
theta = atan2(r, z), theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
u = fx theta_d x / r + cx, v = fy theta_d y / r + cy with r = |(x, y)|.
Stereo/RGB-D observations add the rectified right image's u coordinate ``u_right_px`` (NaN for a monocular
observation) and need ``bf`` = baseline * fx (m px); they exist for pinhole cameras only.

A non-rectified stereo rig (ORB-SLAM3 sec. I-B) has a second camera rigidly attached to the body camera: a pose
problem's ``camera_index`` says which camera saw each observation (0: the camera of ``T_c_w``, 1: the second one),
and the second camera's observations are residuals of their own, projected through the second camera's model
(``intrinsics2``, ``camera_model2``, ``distortion2``) at T_c2_c1 @ T_c_w (ORB-SLAM3
EdgeSE3ProjectXYZOnlyPoseToBody with mTrl; the extrinsic ``T_c2_c1`` is fixed). They are 2-dof (no right
coordinate: ``u_right_px`` NaN).

Paper constants (defaults here) are the ORB-SLAM values; the pipeline passes the configured values.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

#: Values of a problem's ``camera_model``.
CAMERA_PINHOLE = "pinhole"
CAMERA_KANNALA_BRANDT = "kannala_brandt"
CAMERA_MODELS = (CAMERA_PINHOLE, CAMERA_KANNALA_BRANDT)

# Chi-square 95% quantiles for 2 and 3 degrees of freedom (ORB-SLAM, Optimizer.cc; paper appendix).
CHI2_MONO_95 = 5.991
CHI2_STEREO_95 = 7.815


@dataclass
class PoseOnlyProblem:
    """Motion-only BA: one camera pose, fixed 3D points (ORB-SLAM PoseOptimization).

    T_c_w_init: (4, 4) initial pose.
    xyz_w: (N, 3) m, fixed points in the world frame.
    uv_px: (N, 2) observations in the camera model's image (undistorted for "pinhole", raw for "kannala_brandt").
    u_right_px: (N,) right-image u for stereo/RGB-D observations, NaN for monocular ones.
    level: (N,) int pyramid level of each observation; information = 1 / scale_factor**(2 level).
    intrinsics: (4,) fx, fy, cx, cy; bf: baseline * fx (m px), needed only for stereo observations.
    camera_model: "pinhole" or "kannala_brandt" (see the module docstring); distortion: (4,) k1..k4 of a
        Kannala-Brandt camera, None for a pinhole one.
    camera_index: (N,) int, 0 or 1: the camera of each observation in a two-camera rig; None: all camera 0.
    T_c2_c1: (4, 4) the rig's fixed extrinsic (camera 1 -> camera 2), intrinsics2 (4,), camera_model2,
        distortion2 (4,) or None: the second camera (needed when any camera_index is 1).
    rounds / iterations_per_round: ORB-SLAM runs 4 rounds of 10 LM iterations, reclassifying outliers
        with the chi-square gates between rounds (outliers of one round may return as inliers).
    """

    T_c_w_init: F64
    xyz_w: F64
    uv_px: F64
    u_right_px: F64
    level: I64
    intrinsics: F64
    bf: float = 0.0
    scale_factor: float = 1.2
    chi2_mono: float = CHI2_MONO_95
    chi2_stereo: float = CHI2_STEREO_95
    rounds: int = 4
    iterations_per_round: int = 10
    camera_model: str = CAMERA_PINHOLE
    distortion: F64 | None = None
    camera_index: I64 | None = None
    T_c2_c1: F64 | None = None
    intrinsics2: F64 | None = None
    camera_model2: str = CAMERA_PINHOLE
    distortion2: F64 | None = None


@dataclass
class PoseOnlyResult:
    """T_c_w: (4, 4) optimized pose; inliers: (N,) bool; costs are robust costs (sum, px^2 units)."""

    T_c_w: F64
    inliers: B
    cost_initial: float
    cost_final: float
    iterations: int


@dataclass
class InertialTerms:
    """Room for ORB-SLAM3's visual-inertial terms (velocities, biases, preintegrated IMU factors).

    Not used yet: backends reject a problem carrying inertial terms they do not support.
    """

    data: dict[str, Any] = field(default_factory=dict)


@dataclass
class BundleProblem:
    """Local or global bundle adjustment (ORB-SLAM LocalBundleAdjustment / GlobalBundleAdjustemnt).

    T_c_w: (K, 4, 4) initial keyframe poses; pose_fixed: (K,) bool.
    intrinsics: (K, 4) fx, fy, cx, cy per keyframe; bf: (K,) baseline * fx per keyframe (0 for mono).
    xyz_w: (M, 3) m initial points; point_fixed: (M,) bool.
    obs_pose: (E,) int index into poses; obs_point: (E,) int index into points.
    uv_px: (E, 2) observations in the camera model's image; u_right_px: (E,) NaN for monocular; level: (E,) int.
    iterations_first / iterations_second: ORB-SLAM optimizes 5 iterations, removes observations failing
        the chi-square gate (or with the point behind the camera), then optimizes 10 more without them.
    robust: use the Huber kernel (delta = sqrt(chi2)).
    camera_model: "pinhole" or "kannala_brandt" for every keyframe; distortion: (K, 4) k1..k4 per keyframe of a
        Kannala-Brandt camera, None for pinhole ones.
    camera_index: (E,) int, 0 or 1: which camera of a keyframe's rig made each observation; None: all camera 0.
    T_c2_c1: (K, 4, 4) each keyframe's fixed rig extrinsic (camera 1 -> camera 2); intrinsics2: (K, 4);
        camera_model2; distortion2: (K, 4) or None: the second cameras (needed when any camera_index is 1). A
        second-camera observation is projected at T_c2_c1[k] @ T_c_w[k] (ORB-SLAM3 EdgeSE3ProjectXYZToBody).
    """

    T_c_w: F64
    pose_fixed: B
    intrinsics: F64
    bf: F64
    xyz_w: F64
    point_fixed: B
    obs_pose: I64
    obs_point: I64
    uv_px: F64
    u_right_px: F64
    level: I64
    scale_factor: float = 1.2
    chi2_mono: float = CHI2_MONO_95
    chi2_stereo: float = CHI2_STEREO_95
    iterations_first: int = 5
    iterations_second: int = 10
    robust: bool = True
    inertial: InertialTerms | None = None
    camera_model: str = CAMERA_PINHOLE
    distortion: F64 | None = None
    camera_index: I64 | None = None
    T_c2_c1: F64 | None = None
    intrinsics2: F64 | None = None
    camera_model2: str = CAMERA_PINHOLE
    distortion2: F64 | None = None


@dataclass
class BundleResult:
    """T_c_w: (K, 4, 4); xyz_w: (M, 3); outlier: (E,) bool; aborted: stopped early by the abort token."""

    T_c_w: F64
    xyz_w: F64
    outlier: B
    cost_initial: float
    cost_final: float
    iterations: int
    aborted: bool = False


@dataclass
class Sim3Problem:
    """Relative Sim3 between keyframes 1 and 2 from matched points (ORB-SLAM OptimizeSim3, eq. 10-11).

    S_12_init: (4, 4) Sim3 mapping points of camera 2 into camera 1.
    xyz1_c1: (N, 3) m, the match's point of keyframe 1 in camera 1 (fixed).
    xyz2_c2: (N, 3) m, the match's point of keyframe 2 in camera 2 (fixed).
    uv1_px: (N, 2) observation in keyframe 1 of its point; uv2_px: (N, 2) the same in keyframe 2.
    level1, level2: (N,) pyramid levels; intrinsics1/2: (4,) fx fy cx cy.
    camera_model1/2: "pinhole" or "kannala_brandt" (module docstring), the model of keyframe 1's / 2's camera in
        whose image uv1_px / uv2_px lie; distortion1/2: (4,) k1..k4 of a Kannala-Brandt camera, None for pinhole
        (ORB-SLAM3 OptimizeSim3: vSim3->pCamera1 / pCamera2 project each direction).
    The error is bidirectional: uv1 vs project_1(S_12 xyz2_c2) and uv2 vs project_2(S_12^-1 xyz1_c1).
    chi2: ORB-SLAM uses th2 = 10 per direction. fix_scale: stereo/RGB-D (scale observable).
    """

    S_12_init: F64
    xyz1_c1: F64
    xyz2_c2: F64
    uv1_px: F64
    uv2_px: F64
    level1: I64
    level2: I64
    intrinsics1: F64
    intrinsics2: F64
    scale_factor: float = 1.2
    chi2: float = 10.0
    fix_scale: bool = False
    iterations_first: int = 5
    iterations_second: int = 10
    camera_model1: str = CAMERA_PINHOLE
    distortion1: F64 | None = None
    camera_model2: str = CAMERA_PINHOLE
    distortion2: F64 | None = None


@dataclass
class Sim3Result:
    """S_12: (4, 4) optimized Sim3; inliers: (N,) bool."""

    S_12: F64
    inliers: B
    cost_initial: float
    cost_final: float
    iterations: int


@dataclass
class EssentialGraphProblem:
    """Pose-graph optimization over the essential graph (ORB-SLAM OptimizeEssentialGraph).

    S_c_w: (K, 4, 4) initial Sim3 poses (world -> camera, with scale); fixed: (K,) bool (the loop keyframe).
    edge_i, edge_j: (E,) int; S_ij: (E, 4, 4) measured relative transform S_i_j = S_i_w S_j_w^-1 taken from
        the uncorrected (or loop-corrected) poses. Error: log_Sim3(S_ij S_jw S_iw^-1), identity information
        (weights (E,) scale it; 1 by default).
    use_sim3: False for the SE3 variant (stereo/RGB-D): scales are then kept at 1.
    """

    S_c_w: F64
    fixed: B
    edge_i: I64
    edge_j: I64
    S_ij: F64
    weights: F64 | None = None
    use_sim3: bool = True
    iterations: int = 20


@dataclass
class EssentialGraphResult:
    """S_c_w: (K, 4, 4) corrected poses (Sim3 matrices; SE3 when the problem's use_sim3 is False)."""

    S_c_w: F64
    cost_initial: float
    cost_final: float
    iterations: int
