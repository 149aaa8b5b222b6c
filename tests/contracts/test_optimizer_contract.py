"""The optimizer contract: every registered optimizer (first-party or third-party) must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("optimizer")``, each built from its default config
node through slamkit.optim.factory.build_optimizer (inline). Problems come from slamkit.optim.synthetic (seeded,
with known truth, pixel noise sigma = 1 px * 1.2^level and 2-5 % planted wrong matches).

Tolerances (stated here, derived from the noise: with ~300-1000 observations per pose the estimation error of
1 px noise is a few mm / a few 1e-4 rad):
- motion-only BA and BA poses: rotation <= 5e-3 rad, camera centre <= 0.02 m; BA points: median error
  <= 0.04 m and at most half the initial median error.
- relative Sim3: rotation <= 5e-3 rad, translation <= 0.02 m, |log scale| <= 0.01 (exactly 1 with fix_scale).
- essential graph without measurement noise: rotation <= 1e-4 rad, centre <= 1e-3 m, |log scale| <= 1e-4
  (the truth is the exact optimum); with noise: the worst centre error at least 5x smaller than the drift's.
- outliers: recall of planted outliers >= 0.95; clean observations flagged <= 10 % (the chi-square gates are
  95 % quantiles, so ~5 % of clean observations fail them by design) and <= 4 % for Sim3 (its gate, 10 per
  direction, rejects ~1.3 % of clean matches).
- fixed variables exactly unchanged (array_equal).
- backends agree (after convergence, same problem): poses within 1e-3 m and 1e-3 rad.
- camera models: monocular pose and bundle problems also come through a Kannala-Brandt lens (observations are raw
  fisheye pixels, slamkit.optim.synthetic.with_kannala_brandt), with the same tolerances.
- tracking's compiled motion-only BA (slamkit.pipeline.pose_optimization, core's one, the alternative to a
  backend's ``optimize_pose``) meets the motion-only contract on monocular and fisheye problems and agrees with
  every backend.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from slamkit.errors import ProblemError
from slamkit.interfaces import Optimizer
from slamkit.optim.costs import bundle_cost
from slamkit.optim.factory import build_optimizer
from slamkit.optim.synthetic import (
    make_bundle_problem,
    make_essential_graph_problem,
    make_pose_problem,
    make_sim3_problem,
    pose_errors,
    sim3_errors,
    with_kannala_brandt,
)
from slamkit.pipeline.pose_optimization import optimize_pose as compiled_pose_optimization
from slamkit.plugins import ComponentRegistry
from slamkit.problems import (
    CAMERA_KANNALA_BRANDT,
    BundleProblem,
    EssentialGraphProblem,
    InertialTerms,
    PoseOnlyProblem,
    PoseOnlyResult,
)

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("optimizer")]

POSE_ROT_RAD, POSE_POS_M = 5e-3, 0.02
POINT_MEDIAN_M = 0.04
SIM3_ROT_RAD, SIM3_TRANS_M, SIM3_LOG_SCALE = 5e-3, 0.02, 0.01
EG_EXACT_ROT_RAD, EG_EXACT_POS_M, EG_EXACT_LOG_SCALE = 1e-4, 1e-3, 1e-4
RECALL_MIN, FALSE_FLAG_MAX, SIM3_FALSE_FLAG_MAX = 0.95, 0.10, 0.04
AGREE_POS_M, AGREE_ROT_RAD = 1e-3, 1e-3


def _build(name: str) -> Optimizer:
    node = REGISTRY.get("optimizer", name).config_node()
    node["worker"] = "inline"
    return build_optimizer(node, REGISTRY)


@pytest.fixture(scope="module", params=NAMES)
def optimizer(request: pytest.FixtureRequest) -> Optimizer:
    return _build(request.param)


@pytest.fixture(scope="module")
def all_optimizers() -> list[Optimizer]:
    return [_build(name) for name in NAMES]


def _small_bundle(seed: int, stereo_ratio: float = 0.0, **kw: Any) -> tuple[BundleProblem, Any]:
    rng = np.random.default_rng(seed)
    problem, truth = make_bundle_problem(
        rng, n_free=5, n_fixed=3, n_points=400, n_obs=2500, stereo_ratio=stereo_ratio, **kw
    )
    # A few fixed points at their true position (ORB-SLAM fixes none, but the contract covers them).
    problem.point_fixed[:10] = True
    problem.xyz_w[:10] = truth.xyz_w[:10]
    return problem, truth


def _flag_rates(flagged: np.ndarray, planted: np.ndarray) -> tuple[float, float]:
    return float(flagged[planted].mean()), float(flagged[~planted].mean())


# ---- motion-only BA --------------------------------------------------------------------------------------


def check_pose(optimize_pose: Callable[[PoseOnlyProblem], PoseOnlyResult], stereo_ratio: float | str) -> None:
    fisheye = stereo_ratio == "fisheye"
    problem, truth = make_pose_problem(
        np.random.default_rng(11), n_points=300, stereo_ratio=0.0 if fisheye else float(stereo_ratio)
    )
    if fisheye:
        problem = with_kannala_brandt(problem, truth)
    result = optimize_pose(problem)
    rot, pos = pose_errors(result.T_c_w, truth.T_c_w)
    rot0, pos0 = pose_errors(problem.T_c_w_init, truth.T_c_w)
    assert rot <= POSE_ROT_RAD and pos <= POSE_POS_M, (rot, pos, rot0, pos0)
    assert result.inliers.shape == (300,) and result.inliers.dtype == np.bool_
    recall, false_flag = _flag_rates(~result.inliers, truth.outlier)
    assert recall >= RECALL_MIN and false_flag <= FALSE_FLAG_MAX, (recall, false_flag)
    assert result.cost_final < result.cost_initial
    assert result.iterations >= 1


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.5, "fisheye"], ids=["mono", "stereo", "fisheye"])
def test_pose_recovers_truth_and_flags_outliers(optimizer: Optimizer, stereo_ratio: float | str) -> None:
    check_pose(optimizer.optimize_pose, stereo_ratio)


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.5, "fisheye"], ids=["mono", "stereo", "fisheye"])
def test_trackings_compiled_pose_optimization_meets_the_same_contract(stereo_ratio: float | str) -> None:
    """Core's one motion-only BA (slamkit.pipeline.pose_optimization, ``pipeline.tracking.pose_optimization:
    compiled``, monocular, stereo/RGB-D and fisheye) is held to the backends' motion-only contract; ``optimizer``
    runs theirs."""
    check_pose(compiled_pose_optimization, stereo_ratio)


# ---- bundle adjustment -----------------------------------------------------------------------------------


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.5, "fisheye"], ids=["mono", "stereo", "fisheye"])
def test_bundle_recovers_truth_and_respects_fixed(optimizer: Optimizer, stereo_ratio: float | str) -> None:
    fisheye = stereo_ratio == "fisheye"
    problem, truth = _small_bundle(21, 0.0 if fisheye else float(stereo_ratio))
    if fisheye:
        problem = with_kannala_brandt(problem, truth)
    T0, xyz0 = problem.T_c_w.copy(), problem.xyz_w.copy()
    result = optimizer.bundle_adjust(problem)
    assert not result.aborted
    free = ~problem.pose_fixed
    rot, pos = pose_errors(result.T_c_w[free], truth.T_c_w[free])
    assert rot.max() <= POSE_ROT_RAD and pos.max() <= POSE_POS_M, (rot.max(), pos.max())
    err = np.linalg.norm(result.xyz_w - truth.xyz_w, axis=1)
    err0 = np.linalg.norm(xyz0 - truth.xyz_w, axis=1)
    assert np.median(err) <= POINT_MEDIAN_M and np.median(err) <= 0.5 * np.median(err0)
    recall, false_flag = _flag_rates(result.outlier, truth.outlier)
    assert recall >= RECALL_MIN and false_flag <= FALSE_FLAG_MAX, (recall, false_flag)
    # Fixed variables exactly unchanged; the problem itself untouched.
    assert np.array_equal(result.T_c_w[problem.pose_fixed], T0[problem.pose_fixed])
    assert np.array_equal(result.xyz_w[problem.point_fixed], xyz0[problem.point_fixed])
    assert np.array_equal(problem.T_c_w, T0) and np.array_equal(problem.xyz_w, xyz0)
    assert result.cost_final < result.cost_initial
    assert 1 <= result.iterations <= problem.iterations_first + problem.iterations_second


class CountdownToken:
    """An abort token that becomes set after ``checks`` calls of is_set (deterministic mid-run abort)."""

    def __init__(self, checks: int) -> None:
        self.remaining = checks

    def is_set(self) -> bool:
        self.remaining -= 1
        return self.remaining < 0


@pytest.mark.parametrize("checks", [0, 2], ids=["before-start", "after-2-checks"])
def test_bundle_abort_returns_valid_partial_result(optimizer: Optimizer, checks: int) -> None:
    problem, _truth = _small_bundle(22)
    full = optimizer.bundle_adjust(problem)
    result = optimizer.bundle_adjust(problem, abort=CountdownToken(checks))
    assert result.aborted
    assert result.iterations < full.iterations
    assert np.isfinite(result.T_c_w).all() and np.isfinite(result.xyz_w).all()
    assert result.outlier.shape == problem.obs_pose.shape
    assert np.array_equal(result.T_c_w[problem.pose_fixed], problem.T_c_w[problem.pose_fixed])
    cost0 = bundle_cost(problem, problem.T_c_w, problem.xyz_w)
    assert bundle_cost(problem, result.T_c_w, result.xyz_w) <= cost0 * (1 + 1e-9)


# ---- relative Sim3 ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("fix_scale", "fisheye"),
    [(False, False), (True, False), (True, True)],
    ids=["free-scale", "fixed-scale", "fixed-scale-fisheye"],
)
def test_sim3_recovers_truth_and_flags_outliers(optimizer: Optimizer, fix_scale: bool, fisheye: bool) -> None:
    problem, truth = make_sim3_problem(np.random.default_rng(31), n_matches=150, fix_scale=fix_scale)
    if fisheye:  # both keyframes' observations raw Kannala-Brandt pixels (a fisheye rig's loop; ORB-SLAM3 pCamera1/2)
        problem = with_kannala_brandt(problem, truth)
    result = optimizer.optimize_sim3(problem)
    s = float(np.cbrt(np.linalg.det(result.S_12[:3, :3])))
    s_true = float(np.cbrt(np.linalg.det(truth.S_12[:3, :3])))
    R_err = (result.S_12[:3, :3] / s).T @ (truth.S_12[:3, :3] / s_true)
    rot = float(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1)))
    trans = float(np.linalg.norm(result.S_12[:3, 3] - truth.S_12[:3, 3]))
    assert rot <= SIM3_ROT_RAD and trans <= SIM3_TRANS_M, (rot, trans)
    if fix_scale:
        assert abs(s - 1.0) <= 1e-9
    else:
        assert abs(np.log(s / s_true)) <= SIM3_LOG_SCALE
    recall, false_flag = _flag_rates(~result.inliers, truth.outlier)
    assert recall >= RECALL_MIN and false_flag <= SIM3_FALSE_FLAG_MAX, (recall, false_flag)


# ---- essential graph -------------------------------------------------------------------------------------


@pytest.mark.parametrize("use_sim3", [True, False], ids=["sim3", "se3"])
def test_essential_graph_exact_truth(optimizer: Optimizer, use_sim3: bool) -> None:
    problem, truth = make_essential_graph_problem(
        np.random.default_rng(41),
        n_keyframes=150,
        n_edges=200,
        use_sim3=use_sim3,
        noise_rot_rad=0.0,
        noise_trans_m=0.0,
        noise_log_scale=0.0,
    )
    S0 = problem.S_c_w.copy()
    result = optimizer.optimize_essential_graph(problem)
    rot, pos, scale = sim3_errors(result.S_c_w, truth.S_c_w)
    _rot0, pos0, _ = sim3_errors(S0, truth.S_c_w)
    assert pos0.max() > 0.3  # the drift being corrected
    assert rot.max() <= EG_EXACT_ROT_RAD and pos.max() <= EG_EXACT_POS_M and scale.max() <= EG_EXACT_LOG_SCALE
    assert np.array_equal(result.S_c_w[problem.fixed], S0[problem.fixed])
    if not use_sim3:
        assert np.allclose(np.linalg.det(result.S_c_w[:, :3, :3]), 1.0, atol=1e-9)
    assert result.cost_final < result.cost_initial


@pytest.mark.parametrize("use_sim3", [True, False], ids=["sim3", "se3"])
def test_essential_graph_noisy_corrects_drift(optimizer: Optimizer, use_sim3: bool) -> None:
    problem, truth = make_essential_graph_problem(
        np.random.default_rng(42), n_keyframes=200, n_edges=260, use_sim3=use_sim3
    )
    result = optimizer.optimize_essential_graph(problem)
    _, pos, _ = sim3_errors(result.S_c_w, truth.S_c_w)
    _, pos0, _ = sim3_errors(problem.S_c_w, truth.S_c_w)
    assert pos.max() * 5 <= pos0.max(), (pos.max(), pos0.max())


# ---- bad problems ----------------------------------------------------------------------------------------


def _pose() -> PoseOnlyProblem:
    return make_pose_problem(np.random.default_rng(51), n_points=50)[0]


def _bundle() -> BundleProblem:
    return _small_bundle(52)[0]


def _graph() -> EssentialGraphProblem:
    return make_essential_graph_problem(np.random.default_rng(53), n_keyframes=30, n_edges=40)[0]


def _nan_point() -> BundleProblem:
    p = _bundle()
    p.xyz_w[7, 1] = np.nan
    return p


def _behind() -> BundleProblem:
    p = _bundle()
    # Mirror point 5 through every camera observing it: it is now behind all of them.
    cams = p.obs_pose[p.obs_point == 5]
    T = p.T_c_w[cams[0]]
    c = -T[:3, :3].T @ T[:3, 3]
    p.xyz_w[5] = c - 3.0 * T[2, :3]  # 3 m behind the first observing camera, along its optical axis
    for k in cams:
        assert (p.T_c_w[k, 2, :3] @ p.xyz_w[5] + p.T_c_w[k, 2, 3]) < 0
    return p


BAD: dict[str, tuple[str, Callable[[], Any], str]] = {
    "pose-empty": (
        "optimize_pose",
        lambda: replace(
            _pose(),
            xyz_w=np.zeros((0, 3)),
            uv_px=np.zeros((0, 2)),
            u_right_px=np.zeros(0),
            level=np.zeros(0, np.int64),
        ),
        "no observations",
    ),
    "pose-inf-pixel": ("optimize_pose", lambda: replace(_pose(), uv_px=np.full((50, 2), np.inf)), r"uv_px.*inf"),
    "bundle-nan-point": ("bundle_adjust", _nan_point, r"xyz_w: contains NaN or inf at index \(7, 1\)"),
    "bundle-index-out-of-range": (
        "bundle_adjust",
        lambda: replace(_bundle(), obs_point=np.where(np.arange(2500) == 3, 400, _bundle().obs_point)),
        r"obs_point\[3\] = 400 is out of range",
    ),
    "bundle-behind-every-camera": ("bundle_adjust", _behind, "point 5 .* behind every camera"),
    "bundle-no-fixed": (
        "bundle_adjust",
        lambda: replace(_bundle(), pose_fixed=np.zeros(8, bool), point_fixed=np.zeros(400, bool)),
        "no fixed variable",
    ),
    "bundle-inertial": ("bundle_adjust", lambda: replace(_bundle(), inertial=InertialTerms()), "inertial terms"),
    "pose-pinhole-with-distortion": (
        "optimize_pose",
        lambda: replace(_pose(), distortion=np.zeros(4)),
        "distortion: given for a pinhole problem",
    ),
    "pose-unknown-camera-model": (
        "optimize_pose",
        lambda: replace(_pose(), camera_model="fov"),
        "camera_model = 'fov'",
    ),
    "bundle-fisheye-without-distortion": (
        "bundle_adjust",
        lambda: replace(_bundle(), camera_model=CAMERA_KANNALA_BRANDT),
        r"distortion: missing; expected k1..k4 of shape \(8, 4\)",
    ),
    "pose-fisheye-stereo": (
        "optimize_pose",
        lambda: replace(
            _pose(),
            camera_model=CAMERA_KANNALA_BRANDT,
            distortion=np.zeros(4),
            u_right_px=np.where(np.arange(50) == 2, 100.0, np.nan),
        ),
        r"u_right_px\[2\] is a stereo observation in a kannala_brandt problem",
    ),
    "graph-no-fixed": ("optimize_essential_graph", lambda: replace(_graph(), fixed=np.zeros(30, bool)), "no fixed"),
    "sim3-too-few": (
        "optimize_sim3",
        lambda: (lambda p: replace(p, xyz1_c1=p.xyz1_c1[:2]))(make_sim3_problem(np.random.default_rng(54))[0]),
        "at least 3",
    ),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_rejects_bad_problems(optimizer: Optimizer, case: str) -> None:
    method, make, message = BAD[case]
    with pytest.raises(ProblemError, match=message):
        getattr(optimizer, method)(make())


# ---- cross-backend agreement -----------------------------------------------------------------------------


def _pairwise(results: list[np.ndarray], errors: Callable[..., tuple[Any, ...]]) -> None:
    for (a, Ta), (b, Tb) in itertools.combinations(zip(NAMES, results, strict=True), 2):
        err = errors(Ta, Tb)
        rot, pos = float(np.max(err[0])), float(np.max(err[1]))
        assert rot <= AGREE_ROT_RAD and pos <= AGREE_POS_M, f"{a} vs {b}: rot {rot:.3g} rad, pos {pos:.3g} m"


needs_two = pytest.mark.skipif(len(NAMES) < 2, reason=f"only one optimizer registered ({NAMES})")


@pytest.mark.parametrize("kind", ["mono", "fisheye", "stereo"])
def test_backends_agree_with_trackings_compiled_pose_optimization(all_optimizers: list[Optimizer], kind: str) -> None:
    fisheye = kind == "fisheye"
    stereo_ratio = 0.6 if kind == "stereo" else 0.0
    problem, truth = make_pose_problem(np.random.default_rng(67), n_points=300, stereo_ratio=stereo_ratio)
    if fisheye:
        problem = with_kannala_brandt(problem, truth)
    compiled = compiled_pose_optimization(problem).T_c_w
    for name, opt in zip(NAMES, all_optimizers, strict=True):
        rot, pos = pose_errors(opt.optimize_pose(problem).T_c_w, compiled)
        assert rot <= AGREE_ROT_RAD and pos <= AGREE_POS_M, f"{name} vs compiled: rot {rot:.3g} rad, pos {pos:.3g} m"


@needs_two
def test_backends_agree_on_bundle(all_optimizers: list[Optimizer]) -> None:
    problem, _ = _small_bundle(61)
    problem.iterations_first, problem.iterations_second = 10, 30  # run to convergence
    _pairwise([opt.bundle_adjust(problem).T_c_w for opt in all_optimizers], pose_errors)


@needs_two
def test_backends_agree_on_stereo_bundle(all_optimizers: list[Optimizer]) -> None:
    """The 3-dof stereo/RGB-D residual (u, v, u_right; chi2 7.815) in local BA: the backends find the same poses."""
    problem, _ = _small_bundle(68, stereo_ratio=0.6)
    problem.iterations_first, problem.iterations_second = 10, 30  # run to convergence
    _pairwise([opt.bundle_adjust(problem).T_c_w for opt in all_optimizers], pose_errors)


@needs_two
def test_backends_agree_on_pose(all_optimizers: list[Optimizer]) -> None:
    problem, _ = make_pose_problem(np.random.default_rng(62), n_points=300, stereo_ratio=0.3)
    _pairwise([opt.optimize_pose(problem).T_c_w for opt in all_optimizers], pose_errors)


@needs_two
def test_backends_agree_on_fisheye(all_optimizers: list[Optimizer]) -> None:
    problem, truth = make_pose_problem(np.random.default_rng(65), n_points=300)
    fisheye = with_kannala_brandt(problem, truth)
    _pairwise([opt.optimize_pose(fisheye).T_c_w for opt in all_optimizers], pose_errors)
    bundle, bundle_truth = _small_bundle(66)
    fisheye_bundle = with_kannala_brandt(bundle, bundle_truth)
    fisheye_bundle.iterations_first, fisheye_bundle.iterations_second = 10, 30
    _pairwise([opt.bundle_adjust(fisheye_bundle).T_c_w for opt in all_optimizers], pose_errors)


@needs_two
def test_backends_agree_on_sim3(all_optimizers: list[Optimizer]) -> None:
    problem, truth = make_sim3_problem(np.random.default_rng(63), n_matches=150)
    problem.iterations_second = 30
    _pairwise([opt.optimize_sim3(problem).S_12 for opt in all_optimizers], sim3_errors)
    fisheye = with_kannala_brandt(problem, truth)
    _pairwise([opt.optimize_sim3(fisheye).S_12 for opt in all_optimizers], sim3_errors)


@needs_two
@pytest.mark.parametrize("use_sim3", [True, False], ids=["sim3", "se3"])
def test_backends_agree_on_essential_graph(all_optimizers: list[Optimizer], use_sim3: bool) -> None:
    problem, _ = make_essential_graph_problem(
        np.random.default_rng(64), n_keyframes=200, n_edges=260, use_sim3=use_sim3
    )
    problem.iterations = 50
    _pairwise([opt.optimize_essential_graph(problem).S_c_w for opt in all_optimizers], sim3_errors)


# ---- the full-size problems (slow) -----------------------------------------------------------------------


@pytest.mark.slow
def test_full_size_local_ba_and_essential_graph(optimizer: Optimizer) -> None:
    problem, truth = make_bundle_problem(np.random.default_rng(71))
    result = optimizer.bundle_adjust(problem)
    free = ~problem.pose_fixed
    rot, pos = pose_errors(result.T_c_w[free], truth.T_c_w[free])
    assert rot.max() <= POSE_ROT_RAD and pos.max() <= POSE_POS_M
    recall, false_flag = _flag_rates(result.outlier, truth.outlier)
    assert recall >= RECALL_MIN and false_flag <= FALSE_FLAG_MAX
    graph, gtruth = make_essential_graph_problem(np.random.default_rng(72))
    out = optimizer.optimize_essential_graph(graph)
    _, pos, _ = sim3_errors(out.S_c_w, gtruth.S_c_w)
    _, pos0, _ = sim3_errors(graph.S_c_w, gtruth.S_c_w)
    assert pos.max() * 5 <= pos0.max()
