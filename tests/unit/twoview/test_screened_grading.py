"""The screened grading of motion hypotheses (reconstruct.py ``check_motion_screened``, screen.py) gives
``check_motion``'s counts, parallax, mask and points bit for bit, and the initializer's result is the same with it."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from slamkit_twoview import TwoViewInitializer
from slamkit_twoview.decompose import decompose_essential, decompose_homography
from slamkit_twoview.reconstruct import check_motion, check_motion_screened, exact_points
from slamkit_twoview.screen import screen_points

from slamkit.geometry import so3_exp
from slamkit.geometry.so3 import hat

GRADING = {"max_reproj_err_px": 2.0, "max_cos_parallax": 0.99998, "parallax_rank": 50}

# (kind, make_views keywords): general and planar scenes, noisy, with outliers, at parallaxes from ORB-SLAM's
# threshold region (~0.36-1 deg: many near-parallel rays, as fr1_xyz's first frames) to wide baselines
SCENES = [
    ("general", {"noise_px": 1.0, "outlier_fraction": 0.2}),
    ("plane", {"noise_px": 1.0, "outlier_fraction": 0.1}),
    ("general", {"t": (0.03, 0.005, 0.0), "noise_px": 0.5}),
    ("plane", {"t": (0.02, 0.01, 0.0), "noise_px": 1.0, "outlier_fraction": 0.1}),
    ("general", {"t": (0.0, 0.0, 0.5), "noise_px": 1.0}),
    ("general", {"t": (0.001, 0.0, 0.0), "noise_px": 0.3}),
    ("general", {"noise_px": 0.0}),
]


def _motions(views: Any, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The true motion's four essential hypotheses, the eight of its plane homography and some perturbed ones."""
    hyp = decompose_essential(hat(views.t / np.linalg.norm(views.t)) @ views.R)  # E = [t]x R
    motions = list(zip(hyp.R, hyp.t, strict=True))
    normal = np.array([0.0, -1.0, 1.0]) / np.sqrt(2.0)
    H = K @ (views.R + np.outer(views.t, normal) / 3.0) @ np.linalg.inv(K)
    h = decompose_homography(H, K)
    motions += list(zip(h.R, h.t, strict=True))
    rng = np.random.default_rng(3)
    for _ in range(4):
        R = so3_exp(rng.normal(scale=0.01, size=3)) @ views.R
        t = views.t + rng.normal(scale=0.05, size=3) * np.linalg.norm(views.t)
        motions.append((R, t / np.linalg.norm(t)))
    return motions


def _same_check(a: Any, b: Any) -> None:
    assert a.n_good == b.n_good
    assert a.parallax_deg == b.parallax_deg  # bit for bit: it is compared with min_parallax_deg and reported
    np.testing.assert_array_equal(a.triangulated, b.triangulated)


@pytest.mark.parametrize(("kind", "kw"), SCENES)
@pytest.mark.parametrize("seed", [0, 1])
def test_screened_grading_is_check_motions_bit_for_bit(tv: Any, kind: str, kw: dict[str, Any], seed: int) -> None:
    views = tv.make(kind, seed=seed, **kw)
    rng = np.random.default_rng(seed)
    masks = [np.ones(len(views.uv_ref), bool), rng.random(len(views.uv_ref)) < 0.6]
    for R, t in _motions(views, tv.K):
        for inliers in masks:
            exact = check_motion(R, t, tv.K, views.uv_ref, views.uv_cur, inliers, **GRADING)
            screened = check_motion_screened(R, t, tv.K, views.uv_ref, views.uv_cur, inliers, **GRADING)
            _same_check(exact, screened)
            assert np.all(np.isnan(screened.xyz_ref))  # its points are left to exact_points
            points = exact_points(R, t, tv.K, views.uv_ref, views.uv_cur, screened.triangulated)
            np.testing.assert_array_equal(points, exact.xyz_ref)  # NaN where not triangulated, in both


def test_no_inliers_and_a_rank_beyond_the_good_points(tv: Any) -> None:
    views = tv.make("general", seed=2, n=60, noise_px=0.5)
    none = np.zeros(len(views.uv_ref), bool)
    R, t = views.R, views.t / np.linalg.norm(views.t)
    _same_check(
        check_motion(R, t, tv.K, views.uv_ref, views.uv_cur, none, **GRADING),
        check_motion_screened(R, t, tv.K, views.uv_ref, views.uv_cur, none, **GRADING),
    )
    every = np.ones(len(views.uv_ref), bool)
    for rank in (0, 10, 10_000):  # the parallax of the (rank+1)-th point, or of the last good one
        kw = {**GRADING, "parallax_rank": rank}
        _same_check(
            check_motion(R, t, tv.K, views.uv_ref, views.uv_cur, every, **kw),
            check_motion_screened(R, t, tv.K, views.uv_ref, views.uv_cur, every, **kw),
        )


def test_the_screen_leaves_points_at_a_threshold_to_the_exact_path(tv: Any) -> None:
    """A point whose reprojection error is the threshold (to rounding) is flagged unsure, not decided; a clear one is
    decided as the exact path decides it."""
    views = tv.make("general", seed=4, n=50)
    R, t = views.R, views.t
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    P1 = tv.K @ np.eye(4)[:3]
    P2 = tv.K @ T[:3]
    center2 = -R.T @ t
    uv_cur = views.uv_cur.copy()
    uv_cur[0, 0] += 2.0  # about 2 px off: the error is near max_err_px (the point moves too, but less)
    args = (P1, P2, center2, views.uv_ref.copy(), uv_cur)
    _, _, _, good, _, unsure = screen_points(*args, 2.0, 0.99998, 1e-14)
    assert not unsure[1:].any() and good[1:].all()  # noise-free points: certainly good
    # find the threshold that the first point's screened error meets and grade against it exactly
    xyz, *_ = screen_points(*args, 100.0, 0.99998, 1e-14)
    h = P2 @ np.r_[xyz[0], 1.0]
    err = float(np.hypot(h[0] / h[2] - uv_cur[0, 0], h[1] / h[2] - uv_cur[0, 1]))
    _, _, _, _, _, unsure_at = screen_points(*args, err, 0.99998, 1e-14)
    assert unsure_at[0] and not unsure_at[1:].any()


@pytest.mark.parametrize(("kind", "kw"), SCENES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_initializers_result_is_the_same_with_and_without_screening(
    tv: Any, kind: str, kw: dict[str, Any], seed: int
) -> None:
    views = tv.make(kind, seed=seed, **kw)
    a = TwoViewInitializer(screened_grading=False).initialize(
        views.uv_ref, views.uv_cur, tv.K, np.random.default_rng(seed)
    )
    b = TwoViewInitializer(screened_grading=True).initialize(
        views.uv_ref, views.uv_cur, tv.K, np.random.default_rng(seed)
    )
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if field.name == "details":
            assert x.keys() == y.keys()
            for key in x:
                np.testing.assert_array_equal(np.asarray(x[key], dtype=object), np.asarray(y[key], dtype=object))
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y, field.name
