"""The pieces of the twoview initializer: minimal sets, batched H/F fits, ORB-SLAM's scores, decompositions."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from slamkit_twoview.decompose import decompose_essential, decompose_homography
from slamkit_twoview.ransac import (
    draw_minimal_sets,
    fit_models,
    fundamentals_8point,
    hartley_normalization,
    homographies_dlt,
    score_fundamentals,
    score_homographies,
)
from slamkit_twoview.refine import refine_essential, sampson_residuals_px

from slamkit.geometry import hat, so3_exp


def true_homography(tv: Any, views: Any, normal: np.ndarray, d: float) -> np.ndarray:
    """H21 = K (R + t n^T / d) K^-1 for the plane n . x = d in the reference frame."""
    A = views.R + np.outer(views.t, normal / np.linalg.norm(normal)) / d
    H: np.ndarray = tv.K @ A @ np.linalg.inv(tv.K)
    return H / H[2, 2]


def true_fundamental(tv: Any, views: Any) -> np.ndarray:
    K_inv = np.linalg.inv(tv.K)
    F: np.ndarray = K_inv.T @ hat(views.t) @ views.R @ K_inv
    return F / np.linalg.norm(F)


def contains_motion(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray) -> bool:
    t_unit = t_true / np.linalg.norm(t_true)
    return any(np.allclose(R[i], R_true, atol=1e-8) and np.allclose(t[i], t_unit, atol=1e-8) for i in range(len(R)))


def test_minimal_sets_are_distinct_in_range_and_deterministic() -> None:
    a = draw_minimal_sets(30, 500, 8, np.random.default_rng(5))
    b = draw_minimal_sets(30, 500, 8, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (500, 8) and a.min() >= 0 and a.max() < 30
    assert all(len(set(row)) == 8 for row in a.tolist())
    counts = np.bincount(a.ravel(), minlength=30)  # uniform: each index in ~8/30 of the sets
    assert counts.min() > 0.6 * 500 * 8 / 30 and counts.max() < 1.4 * 500 * 8 / 30


def test_hartley_normalization_centres_and_scales() -> None:
    uv = np.random.default_rng(0).uniform(0, 640, (100, 2))
    n, T = hartley_normalization(uv)
    np.testing.assert_allclose(n.mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(n, axis=1).mean() == pytest.approx(np.sqrt(2.0))
    np.testing.assert_allclose((np.c_[uv, np.ones(100)] @ T.T)[:, :2], n)


@pytest.mark.parametrize("k", [4, 8])
def test_batched_dlt_recovers_the_exact_homography(tv: Any, k: int) -> None:
    normal = np.array([0.0, -1.0, 1.0])
    views = tv.make("plane", plane_normal=tuple(normal), plane_distance_m=3.0)
    H_true = true_homography(tv, views, normal, 3.0)
    sets = draw_minimal_sets(len(views.uv_ref), 5, k, np.random.default_rng(0))
    H = homographies_dlt(views.uv_ref[sets], views.uv_cur[sets])
    for Hi in H:
        np.testing.assert_allclose(Hi / Hi[2, 2], H_true, rtol=1e-6, atol=1e-9)


def test_batched_8point_gives_rank2_matrices_of_the_true_epipolar_geometry(tv: Any) -> None:
    views = tv.make("general")
    sets = draw_minimal_sets(len(views.uv_ref), 5, 8, np.random.default_rng(0))
    n1, T1 = hartley_normalization(views.uv_ref)
    n2, T2 = hartley_normalization(views.uv_cur)
    F = T2.T @ fundamentals_8point(n1[sets], n2[sets]) @ T1
    F_true = true_fundamental(tv, views)
    for Fi in F:
        assert np.linalg.svd(Fi, compute_uv=False)[2] < 1e-12 * np.linalg.norm(Fi)
        Fi = Fi / np.linalg.norm(Fi) * np.sign(np.sum(Fi * F_true))
        np.testing.assert_allclose(Fi, F_true, atol=1e-8)


def reference_scores(H21: np.ndarray, F21: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> tuple[float, ...]:
    """ORB-SLAM2's CheckHomography / CheckFundamental, point by point (sigma = 1)."""
    H12 = np.linalg.inv(H21)
    s_h = s_f = 0.0
    in_h = in_f = 0
    for (u1, v1), (u2, v2) in zip(uv1, uv2, strict=True):
        x1, x2 = np.array([u1, v1, 1.0]), np.array([u2, v2, 1.0])
        ok = True
        for Hm, src, dst in ((H12, x2, x1), (H21, x1, x2)):
            p = Hm @ src
            chi = (p[0] / p[2] - dst[0]) ** 2 + (p[1] / p[2] - dst[1]) ** 2
            if chi > 5.991:
                ok = False
            else:
                s_h += 5.991 - chi
        in_h += ok
        ok = True
        for line, pt in ((F21 @ x1, x2), (F21.T @ x2, x1)):
            chi = (line @ pt) ** 2 / (line[0] ** 2 + line[1] ** 2)
            if chi > 3.841:
                ok = False
            else:
                s_f += 5.991 - chi
        in_f += ok
    return s_h, float(in_h), s_f, float(in_f)


def test_scores_match_orbslam_check_functions_point_by_point(tv: Any) -> None:
    views = tv.make("general", noise_px=1.5, outlier_fraction=0.3)
    normal = np.array([0.0, 0.0, 1.0])
    H = true_homography(tv, views, normal, 5.0)  # fits part of the points only
    F = true_fundamental(tv, views)
    s_h, in_h = score_homographies(H[None], views.uv_ref, views.uv_cur, 1.0, 5.991, 5.991)
    s_f, in_f = score_fundamentals(F[None], views.uv_ref, views.uv_cur, 1.0, 3.841, 5.991)
    ref = reference_scores(H, F, views.uv_ref, views.uv_cur)
    assert 0 < in_h.sum() < len(views.uv_ref) and 0 < in_f.sum() < len(views.uv_ref)
    np.testing.assert_allclose([s_h[0], in_h.sum(), s_f[0], in_f.sum()], ref, rtol=1e-9)


def test_sigma_scales_the_chi_square_test(tv: Any) -> None:
    views = tv.make("general", noise_px=1.0)
    F = true_fundamental(tv, views)[None]
    _, in1 = score_fundamentals(F, views.uv_ref, views.uv_cur, 1.0, 3.841, 5.991)
    _, in2 = score_fundamentals(F, views.uv_ref, views.uv_cur, 2.0, 3.841, 5.991)
    assert in2.sum() > in1.sum()
    assert np.all(in2[0][in1[0]])  # a looser test keeps every earlier inlier


def test_singular_homography_scores_zero_instead_of_failing(tv: Any) -> None:
    views = tv.make("general")
    H = np.zeros((1, 3, 3))
    H[0, 0, 0] = 1.0  # rank 1
    scores, inliers = score_homographies(H, views.uv_ref, views.uv_cur, 1.0, 5.991, 5.991)
    assert scores[0] == 0.0 and not inliers.any()


def test_fit_models_is_deterministic_and_finds_the_inliers(tv: Any) -> None:
    views = tv.make("general", noise_px=0.5, outlier_fraction=0.25)
    sets = draw_minimal_sets(len(views.uv_ref), 200, 8, np.random.default_rng(1))
    kw: dict[str, Any] = {"sigma_px": 1.0, "T_H": 5.991, "T_F": 3.841, "gamma": 5.991, "h_points_per_set": 8}
    h, f = fit_models(views.uv_ref, views.uv_cur, sets, refine=False, **kw)
    _, f2 = fit_models(views.uv_ref, views.uv_cur, sets, refine=False, **kw)
    np.testing.assert_array_equal(f.matrix, f2.matrix)
    assert f.score > h.score  # a general scene is explained by F, not H
    assert f.inliers[views.outlier].mean() < 0.1 and f.inliers[~views.outlier].mean() > 0.9
    _, f_ref = fit_models(views.uv_ref, views.uv_cur, sets, refine=True, **kw)
    assert f_ref.score >= f.score  # the refit is kept only when it scores higher


@pytest.mark.parametrize("seed", range(5))
def test_faugeras_decomposition_contains_the_true_motion(tv: Any, seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = so3_exp(rng.normal(scale=0.2, size=3))
    t = rng.normal(size=3)
    normal = rng.normal(size=3) + np.array([0.0, 0.0, 3.0])
    normal /= np.linalg.norm(normal)
    d = rng.uniform(1.0, 5.0)
    H = tv.K @ (R + np.outer(t, normal) / d) @ np.linalg.inv(tv.K)
    for scale in (1.0, -2.5):  # H is known up to any scale, including its sign
        hyp = decompose_homography(scale * H, tv.K)
        assert hyp.R.shape == (8, 3, 3) and hyp.t.shape == (8, 3) and hyp.n_plane is not None
        np.testing.assert_allclose(np.linalg.det(hyp.R), 1.0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(hyp.t, axis=1), 1.0)
        assert contains_motion(hyp.R, hyp.t, R, t)
        # every hypothesis reproduces H up to scale with its own plane: A = d' R + t' n^T
        A = np.linalg.solve(tv.K, H @ tv.K)
        for Ri, ti, ni in zip(hyp.R, hyp.t, hyp.n_plane, strict=True):
            M = np.c_[Ri.ravel(), np.outer(ti, ni).ravel()]
            coef = np.linalg.lstsq(M, A.ravel(), rcond=None)[0]
            np.testing.assert_allclose(M @ coef, A.ravel(), atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_essential_decomposition_contains_the_true_motion(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = so3_exp(rng.normal(scale=0.5, size=3))
    t = rng.normal(size=3)
    for scale in (1.0, -0.3):
        hyp = decompose_essential(scale * hat(t) @ R)
        np.testing.assert_allclose(np.linalg.det(hyp.R), 1.0, atol=1e-9)
        assert contains_motion(hyp.R, hyp.t, R, t)


def test_essential_refinement_reaches_the_true_motion_from_a_perturbed_start(tv: Any) -> None:
    views = tv.make("general")
    t_unit = views.t / np.linalg.norm(views.t)
    R0 = so3_exp(np.array([0.01, -0.015, 0.01])) @ views.R
    t0 = t_unit + np.array([0.05, -0.08, 0.03])
    R, t = refine_essential(R0, t0, tv.K, views.uv_ref, views.uv_cur)
    assert tv.rot_err_deg(R, views.R) < 1e-5 and tv.dir_err_deg(t, views.t) < 1e-5
    F = np.linalg.inv(tv.K).T @ hat(t) @ R @ np.linalg.inv(tv.K)
    assert np.abs(sampson_residuals_px(F, views.uv_ref, views.uv_cur)).max() < 1e-6


def _numpy_transfer_sq(H: np.ndarray, x_from: np.ndarray, x_to: np.ndarray) -> np.ndarray:
    """The numpy expression the compiled homography scoring replaced (ransac.py before the kernels)."""
    p = x_from[None, :, 0, None] * H[:, None, :, 0] + x_from[None, :, 1, None] * H[:, None, :, 1] + H[:, None, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = p[..., :2] / p[..., 2:3]
    d2: np.ndarray = np.sum((proj - x_to) ** 2, axis=-1)
    return d2


def _numpy_rho(chi2: np.ndarray, threshold: float, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    ok = chi2 <= threshold
    return np.where(ok, gamma - chi2, 0.0), ok


def _numpy_scores(
    model: str, M: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, T: float, gamma: float
) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM's CheckHomography / CheckFundamental as numpy expressions (sigma 1 px)."""
    from slamkit_twoview.ransac import adjugate

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if model == "H":
            s_a, ok_a = _numpy_rho(_numpy_transfer_sq(M, uv1, uv2), T, gamma)
            s_b, ok_b = _numpy_rho(_numpy_transfer_sq(adjugate(M), uv2, uv1), T, gamma)
        else:
            l2 = uv1[None, :, 0, None] * M[:, None, :, 0] + uv1[None, :, 1, None] * M[:, None, :, 1] + M[:, None, :, 2]
            l1 = uv2[None, :, 0, None] * M[:, None, 0, :] + uv2[None, :, 1, None] * M[:, None, 1, :] + M[:, None, 2, :]
            num2 = l2[..., 0] * uv2[:, 0] + l2[..., 1] * uv2[:, 1] + l2[..., 2]
            num1 = l1[..., 0] * uv1[:, 0] + l1[..., 1] * uv1[:, 1] + l1[..., 2]
            s_b, ok_b = _numpy_rho(num2 * num2 / (l2[..., 0] ** 2 + l2[..., 1] ** 2), T, gamma)
            s_a, ok_a = _numpy_rho(num1 * num1 / (l1[..., 0] ** 2 + l1[..., 1] ** 2), T, gamma)
    return (s_a + s_b).sum(axis=1), ok_a & ok_b


@pytest.mark.parametrize("scene", ["general", "plane"])
def test_compiled_scores_are_the_numpy_scores_bit_for_bit(tv: Any, scene: str) -> None:
    """The compiled scoring (kernels.py) gives ORB-SLAM's scores and inlier masks exactly as the numpy expressions
    did, degenerate hypotheses (rank-deficient, a zero row: NaN and inf errors) included."""
    views = tv.make(scene, noise_px=0.8, outlier_fraction=0.3)
    uv1, uv2 = views.uv_ref, views.uv_cur
    sets = draw_minimal_sets(len(uv1), 64, 8, np.random.default_rng(3))
    n1, T1 = hartley_normalization(uv1)
    n2, T2 = hartley_normalization(uv2)
    H = np.linalg.inv(T2) @ homographies_dlt(n1[sets], n2[sets]) @ T1
    F = T2.T @ fundamentals_8point(n1[sets], n2[sets]) @ T1
    H[0] = 0.0  # every transfer is 0/0
    H[1, 2] = 0.0  # points sent to infinity
    F[0] = 0.0  # no epipolar line at all (0/0)
    F[1, 2, :2] = 0.0  # epipolar lines in image 1 with a zero normal
    for model, M, T in (("H", H, 5.991), ("F", F, 3.841)):
        scorer = score_homographies if model == "H" else score_fundamentals
        scores, inliers = scorer(M, uv1, uv2, 1.0, T, 5.991)
        ref_scores, ref_inliers = _numpy_scores(model, M, uv1, uv2, T, 5.991)
        assert scores.tobytes() == ref_scores.tobytes()
        np.testing.assert_array_equal(inliers, ref_inliers)
        assert inliers[2:].any() and not inliers[0].any()


def test_fit_models_in_two_threads_is_the_serial_fit(tv: Any) -> None:
    """parallel (ORB-SLAM's two threads) changes where F is fitted, not what is found."""
    views = tv.make("general", noise_px=0.5, outlier_fraction=0.25)
    sets = draw_minimal_sets(len(views.uv_ref), 200, 8, np.random.default_rng(5))
    kw: dict[str, Any] = {"sigma_px": 1.0, "T_H": 5.991, "T_F": 3.841, "gamma": 5.991, "h_points_per_set": 8}
    serial = fit_models(views.uv_ref, views.uv_cur, sets, refine=True, parallel=False, **kw)
    threaded = fit_models(views.uv_ref, views.uv_cur, sets, refine=True, parallel=True, **kw)
    for a, b in zip(serial, threaded, strict=True):
        assert a.matrix.tobytes() == b.matrix.tobytes() and a.score == b.score and a.iteration == b.iteration
        np.testing.assert_array_equal(a.inliers, b.inliers)
