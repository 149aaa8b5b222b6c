"""validate_*: valid synthetic problems pass; each defect raises ProblemError naming the array, index and expectation."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from slamkit.errors import ProblemError
from slamkit.optim.synthetic import (
    make_bundle_problem,
    make_essential_graph_problem,
    make_pose_problem,
    make_sim3_problem,
)
from slamkit.optim.validation import (
    validate_bundle_problem,
    validate_essential_graph_problem,
    validate_pose_problem,
    validate_sim3_problem,
)
from slamkit.problems import BundleProblem, EssentialGraphProblem, InertialTerms, PoseOnlyProblem, Sim3Problem


def pose() -> PoseOnlyProblem:
    return make_pose_problem(np.random.default_rng(1), n_points=40, stereo_ratio=0.5)[0]


def bundle() -> BundleProblem:
    return make_bundle_problem(np.random.default_rng(2), n_free=3, n_fixed=2, n_points=100, n_obs=400)[0]


def sim3() -> Sim3Problem:
    return make_sim3_problem(np.random.default_rng(3), n_matches=30)[0]


def graph() -> EssentialGraphProblem:
    return make_essential_graph_problem(np.random.default_rng(4), n_keyframes=20, n_edges=25)[0]


def test_valid_problems_pass() -> None:
    validate_pose_problem(pose())
    validate_bundle_problem(bundle())
    validate_sim3_problem(sim3())
    validate_essential_graph_problem(graph())
    validate_essential_graph_problem(
        make_essential_graph_problem(np.random.default_rng(4), n_keyframes=20, n_edges=25, use_sim3=False)[0]
    )


def _set(problem: Any, name: str, index: Any, value: Any) -> Any:
    arr = np.array(getattr(problem, name), copy=True)
    arr[index] = value
    return replace(problem, **{name: arr})


def _rotation_not_orthonormal() -> BundleProblem:
    p = bundle()
    p.T_c_w[2, 0, 0] += 0.1
    return p


def _disconnected() -> EssentialGraphProblem:
    p = graph()
    keep = ~((p.edge_i >= 15) ^ (p.edge_j >= 15))  # drop every edge crossing 14 | 15 (incl. the loop edge)
    return replace(p, edge_i=p.edge_i[keep], edge_j=p.edge_j[keep], S_ij=p.S_ij[keep])


def _free_point_unseen() -> BundleProblem:
    p = bundle()
    keep = p.obs_point != 17
    return replace(
        p,
        obs_pose=p.obs_pose[keep],
        obs_point=p.obs_point[keep],
        uv_px=p.uv_px[keep],
        u_right_px=p.u_right_px[keep],
        level=p.level[keep],
    )


CASES: dict[str, tuple[Callable[[Any], None], Callable[[], Any], str]] = {
    "pose-T-nan": (validate_pose_problem, lambda: _set(pose(), "T_c_w_init", (0, 3), np.nan), r"T_c_w_init: contains"),
    "pose-shape": (validate_pose_problem, lambda: replace(pose(), uv_px=pose().uv_px[:5]), r"uv_px: expected shape"),
    "pose-level-negative": (validate_pose_problem, lambda: _set(pose(), "level", 4, -1), r"level\[4\] = -1"),
    "pose-level-float": (
        validate_pose_problem,
        lambda: replace(pose(), level=pose().level.astype(float)),
        "integer array",
    ),
    "pose-stereo-without-bf": (validate_pose_problem, lambda: replace(pose(), bf=0.0), r"stereo observation.*bf"),
    "pose-all-behind": (
        validate_pose_problem,
        lambda: (lambda p: replace(p, T_c_w_init=np.diag([1.0, -1.0, -1.0, 1.0]) @ p.T_c_w_init))(pose()),
        "every one of the 40 points is behind",
    ),
    "pose-fx-zero": (validate_pose_problem, lambda: _set(pose(), "intrinsics", 0, 0.0), "fx, fy > 0"),
    "pose-u-right-inf": (validate_pose_problem, lambda: _set(pose(), "u_right_px", 2, np.inf), r"u_right_px.*inf"),
    "bundle-rotation": (validate_bundle_problem, _rotation_not_orthonormal, r"T_c_w\[2\].*not a rotation"),
    "bundle-obs-pose-range": (validate_bundle_problem, lambda: _set(bundle(), "obs_pose", 9, 5), r"obs_pose\[9\] = 5"),
    "bundle-negative-index": (
        validate_bundle_problem,
        lambda: _set(bundle(), "obs_point", 0, -1),
        r"obs_point\[0\] = -1 is out of range",
    ),
    "bundle-unseen-point": (validate_bundle_problem, _free_point_unseen, "free point 17 has no observations"),
    "bundle-inertial": (validate_bundle_problem, lambda: replace(bundle(), inertial=InertialTerms()), "inertial"),
    "bundle-fixed-not-bool": (
        validate_bundle_problem,
        lambda: replace(bundle(), pose_fixed=bundle().pose_fixed.astype(int)),
        "pose_fixed: expected a bool array",
    ),
    "bundle-scale-factor": (validate_bundle_problem, lambda: replace(bundle(), scale_factor=-1.2), "scale_factor"),
    "sim3-behind": (validate_sim3_problem, lambda: _set(sim3(), "xyz2_c2", (4, 2), -1.0), r"xyz2_c2\[4\].*behind"),
    "sim3-fix-scale-mismatch": (
        validate_sim3_problem,
        lambda: replace(sim3(), fix_scale=True),
        "fix_scale is True",
    ),
    "sim3-reflection": (
        validate_sim3_problem,
        lambda: replace(sim3(), S_12_init=np.diag([1.0, 1.0, -1.0, 1.0])),
        "proper rotation",
    ),
    "graph-self-loop": (validate_essential_graph_problem, lambda: _set(graph(), "edge_j", 3, 3), "edge 3 joins"),
    "graph-disconnected": (
        validate_essential_graph_problem,
        _disconnected,
        "keyframe 15 is not connected by edges to any fixed keyframe",
    ),
    "graph-weights": (
        validate_essential_graph_problem,
        lambda: replace(graph(), weights=np.zeros(25)),
        r"weights\[0\] = 0",
    ),
    "graph-se3-with-scale": (
        validate_essential_graph_problem,
        lambda: replace(graph(), use_sim3=False),
        r"S_c_w\[\d+\].*not a rotation",
    ),
}


@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
def test_defects_are_rejected_with_a_clear_message(case: str) -> None:
    validate, make, message = CASES[case]
    with pytest.raises(ProblemError, match=message):
        validate(make())
