"""ORB-SLAM's automatic map initialization from two views (Mur-Artal et al. T-RO 2015, sec. IV).

Steps 2-4 of the paper: H and F by RANSAC on shared minimal sets (ransac.py), model selection by
R_H = S_H / (S_H + S_F), motion hypotheses (decompose.py) graded by triangulation and accepted only
with a clear winner (reconstruct.py). Matching (step 1), the full BA (step 5) and the median-depth
scaling are the pipeline's job.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.geometry.so3 import hat
from slamkit.interfaces import TwoViewResult
from slamkit_twoview.decompose import (
    MotionHypotheses,
    decompose_essential,
    decompose_homography,
    homography_singular_values,
)
from slamkit_twoview.ransac import (
    SET_SIZE,
    ModelFit,
    draw_minimal_sets,
    fit_models,
    model_pool,
    score_fundamentals,
)
from slamkit_twoview.reconstruct import (
    HypothesisCheck,
    Selection,
    check_motion,
    check_motion_screened,
    exact_points,
    pose_matrix,
    select_from_fundamental,
    select_from_homography,
)
from slamkit_twoview.refine import refine_essential

F64 = NDArray[np.float64]


def _check(ok: bool, key: str, expected: str, value: Any) -> None:
    if not ok:
        raise ConfigError(f"initializer.{key}: expected {expected}, got {value!r}")


def _number(value: Any, key: str) -> float:
    """A finite real config value as float, else ConfigError naming ``initializer.<key>``."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ConfigError(f"initializer.{key}: expected a number, got {value!r}")
    if not np.isfinite(value):
        raise ConfigError(f"initializer.{key}: expected a finite number, got {value!r}")
    return float(value)


class TwoViewInitializer:
    """``initializer=twoview``: implements slamkit.interfaces.Initializer.

    Every threshold is a config value; defaults are the paper's / ORB-SLAM2's (see plugin.py for the
    sources). Stateless between calls: each ``initialize`` is a pure function of its inputs and ``rng``.
    """

    def __init__(
        self,
        ransac_iterations: int = 200,
        sigma_px: float = 1.0,
        T_H: float = 5.991,
        T_F: float = 3.841,
        gamma: float = 5.991,
        rh_threshold: float = 0.45,
        h_points_per_set: int = 8,
        refine_on_inliers: bool = True,
        min_parallax_deg: float = 1.0,
        min_triangulated: int = 50,
        min_good_fraction: float = 0.9,
        h_second_best_ratio: float = 0.75,
        f_similar_ratio: float = 0.7,
        max_reproj_err_sigmas: float = 2.0,
        max_cos_parallax: float = 0.99998,
        parallax_rank: int = 50,
        min_singular_ratio: float = 1.00001,
        parallel_models: bool = True,
        screened_grading: bool = True,
    ) -> None:
        numbers = {
            "ransac_iterations": ransac_iterations,
            "sigma_px": sigma_px,
            "T_H": T_H,
            "T_F": T_F,
            "gamma": gamma,
            "rh_threshold": rh_threshold,
            "h_points_per_set": h_points_per_set,
            "min_parallax_deg": min_parallax_deg,
            "min_triangulated": min_triangulated,
            "min_good_fraction": min_good_fraction,
            "h_second_best_ratio": h_second_best_ratio,
            "f_similar_ratio": f_similar_ratio,
            "max_reproj_err_sigmas": max_reproj_err_sigmas,
            "max_cos_parallax": max_cos_parallax,
            "parallax_rank": parallax_rank,
            "min_singular_ratio": min_singular_ratio,
        }
        v = {key: _number(value, key) for key, value in numbers.items()}
        _check(
            v["ransac_iterations"].is_integer() and v["ransac_iterations"] >= 1,
            "ransac_iterations",
            "an integer >= 1",
            ransac_iterations,
        )
        for key in ("sigma_px", "T_H", "T_F", "gamma", "max_reproj_err_sigmas"):
            _check(v[key] > 0, key, "a number > 0", v[key])
        _check(0.0 < v["rh_threshold"] < 1.0, "rh_threshold", "a ratio in (0, 1)", rh_threshold)
        _check(v["h_points_per_set"] in (4.0, 8.0), "h_points_per_set", "4 or 8", h_points_per_set)
        _check(v["min_parallax_deg"] >= 0, "min_parallax_deg", "a number >= 0", min_parallax_deg)
        for key in ("min_triangulated", "parallax_rank"):
            _check(v[key].is_integer() and v[key] >= 0, key, "an integer >= 0", v[key])
        for key in ("min_good_fraction", "h_second_best_ratio", "f_similar_ratio"):
            _check(0.0 < v[key] <= 1.0, key, "a ratio in (0, 1]", v[key])
        _check(0.0 < v["max_cos_parallax"] < 1.0, "max_cos_parallax", "a cosine in (0, 1)", max_cos_parallax)
        _check(v["min_singular_ratio"] >= 1.0, "min_singular_ratio", "a ratio >= 1", min_singular_ratio)
        _check(isinstance(refine_on_inliers, bool), "refine_on_inliers", "true or false", refine_on_inliers)
        _check(isinstance(parallel_models, bool), "parallel_models", "true or false", parallel_models)
        _check(isinstance(screened_grading, bool), "screened_grading", "true or false", screened_grading)
        self.ransac_iterations = int(ransac_iterations)
        self.sigma_px = float(sigma_px)
        self.T_H = float(T_H)
        self.T_F = float(T_F)
        self.gamma = float(gamma)
        self.rh_threshold = float(rh_threshold)
        self.h_points_per_set = int(h_points_per_set)
        self.refine_on_inliers = bool(refine_on_inliers)
        self.parallel_models = bool(parallel_models)
        self.screened_grading = bool(screened_grading)
        self.min_parallax_deg = float(min_parallax_deg)
        self.min_triangulated = int(min_triangulated)
        self.min_good_fraction = float(min_good_fraction)
        self.h_second_best_ratio = float(h_second_best_ratio)
        self.f_similar_ratio = float(f_similar_ratio)
        self.max_reproj_err_px = float(max_reproj_err_sigmas) * self.sigma_px
        self.max_cos_parallax = float(max_cos_parallax)
        self.parallax_rank = int(parallax_rank)
        self.min_singular_ratio = float(min_singular_ratio)

    # ------------------------------------------------------------------ public API

    def initialize(self, uv_ref_px: F64, uv_cur_px: F64, K: F64, rng: np.random.Generator) -> TwoViewResult:
        """Attempt a two-view reconstruction from M matches.

        uv_ref_px, uv_cur_px: (M, 2) undistorted px of the same matches in the reference and current
        frames; K: (3, 3) pinhole intrinsics of the undistorted image; rng: draws the RANSAC sets (the
        result is deterministic for a given rng state). Returns a TwoViewResult with T_cur_ref (unit
        translation), xyz_ref (M, 3) in the reference camera (NaN where not triangulated) and details;
        or success=False with the reason(s). Raises ValueError for malformed input (shapes, NaN, K).
        """
        uv1, uv2, Km = _validated(uv_ref_px, uv_cur_px, K, rng)
        n_matches = uv1.shape[0]
        needed = max(SET_SIZE, self.min_triangulated)
        if n_matches < needed:
            return TwoViewResult(
                False,
                f"too few matches: {n_matches} < {needed} (8 for a minimal set, min_triangulated {self.min_triangulated})",
                details={"n_matches": n_matches},
            )

        sets = draw_minimal_sets(n_matches, self.ransac_iterations, SET_SIZE, rng)
        fit_h, fit_f = fit_models(
            uv1,
            uv2,
            sets,
            sigma_px=self.sigma_px,
            T_H=self.T_H,
            T_F=self.T_F,
            gamma=self.gamma,
            h_points_per_set=self.h_points_per_set,
            refine=self.refine_on_inliers,
            parallel=self.parallel_models,
        )
        total = fit_h.score + fit_f.score
        r_h = fit_h.score / total if total > 0 else 0.0
        details: dict[str, Any] = {
            "n_matches": n_matches,
            "S_H": fit_h.score,
            "S_F": fit_f.score,
            "R_H": r_h,
            "n_inliers_H": int(fit_h.inliers.sum()),
            "n_inliers_F": int(fit_f.inliers.sum()),
            "H21": fit_h.matrix,
            "F21": fit_f.matrix,
        }
        if total <= 0:
            return TwoViewResult(False, "no model fits: both RANSAC scores are 0", details=details)
        # The homography when R_H > rh_threshold (ORB-SLAM3: 0.50; paper sec. IV-3: 0.45), else F.
        if r_h > self.rh_threshold:
            return self._reconstruct_h(fit_h, uv1, uv2, Km, details)
        return self._reconstruct_f(fit_f, uv1, uv2, Km, details)

    # ------------------------------------------------------------------ the two branches

    def _reconstruct_h(self, fit: ModelFit, uv1: F64, uv2: F64, K: F64, details: dict[str, Any]) -> TwoViewResult:
        d = homography_singular_values(fit.matrix, K)
        details["singular_values_H"] = d
        with np.errstate(divide="ignore", invalid="ignore"):
            r12, r23 = d[0] / d[1], d[1] / d[2]
        if not (r12 >= self.min_singular_ratio and r23 >= self.min_singular_ratio):
            # ORB-SLAM2 ReconstructH: equal singular values leave the decomposition undefined.
            reason = (
                f"homography: singular values of K^-1 H K nearly equal (d1/d2 = {r12:.6g}, d2/d3 = {r23:.6g}, "
                f"need >= {self.min_singular_ratio}): no parallax (pure rotation or distant plane)"
            )
            return TwoViewResult(False, reason, model="H", details=details)
        hyp = decompose_homography(fit.matrix, K)
        checks = self._grade(hyp, uv1, uv2, K, fit.inliers)
        sel = select_from_homography(
            checks,
            int(fit.inliers.sum()),
            second_best_ratio=self.h_second_best_ratio,
            min_good_fraction=self.min_good_fraction,
            min_triangulated=self.min_triangulated,
            min_parallax_deg=self.min_parallax_deg,
        )
        return self._result("H", hyp, checks, sel, details, uv1, uv2, K)

    def _reconstruct_f(self, fit: ModelFit, uv1: F64, uv2: F64, K: F64, details: dict[str, Any]) -> TwoViewResult:
        if self.refine_on_inliers:
            fit = self._refine_on_essential_manifold(fit, uv1, uv2, K)
            details["S_F_refined"] = fit.score
        E21 = K.T @ fit.matrix @ K
        hyp = decompose_essential(E21)
        checks = self._grade(hyp, uv1, uv2, K, fit.inliers)
        sel = select_from_fundamental(
            checks,
            int(fit.inliers.sum()),
            similar_ratio=self.f_similar_ratio,
            min_good_fraction=self.min_good_fraction,
            min_triangulated=self.min_triangulated,
            min_parallax_deg=self.min_parallax_deg,
        )
        return self._result("F", hyp, checks, sel, details, uv1, uv2, K)

    def _refine_on_essential_manifold(self, fit: ModelFit, uv1: F64, uv2: F64, K: F64) -> ModelFit:
        """F replaced by the Sampson-optimal essential matrix of its inliers, re-scored (new inlier set).

        Kept whatever its score: a 5-dof E scores a little below a 7-dof F on the same data even when
        its motion is better, and the refinement only ever lowers the Sampson cost of the inliers.
        """
        idx = np.flatnonzero(fit.inliers)
        if idx.size < SET_SIZE:
            return fit
        hyp = decompose_essential(K.T @ fit.matrix @ K)
        R, t = refine_essential(hyp.R[0], hyp.t[0], K, uv1[idx], uv2[idx])
        K_inv = np.linalg.inv(K)
        F = K_inv.T @ hat(t) @ R @ K_inv
        scores, inliers = score_fundamentals(F[None], uv1, uv2, self.sigma_px, self.T_F, self.gamma)
        return ModelFit(F, float(scores[0]), inliers[0], fit.iteration)

    def _grade(
        self, hyp: MotionHypotheses, uv1: F64, uv2: F64, K: F64, inliers: NDArray[np.bool_]
    ) -> list[HypothesisCheck]:
        """Paper sec. IV-4: rather than Faugeras' visibility test (fragile at low parallax), triangulate every
        hypothesis and count the points that are good under it. With ``parallel_models`` the second half of the
        hypotheses (4 of H's 8) is graded in the F-fitting thread meanwhile (its batched triangulation SVDs release
        the GIL); each check is a pure function of its hypothesis, so the list is the same either way. With
        ``screened_grading`` each check is ``check_motion_screened``'s (the same counts, parallax and mask; its points are
        computed by ``_result`` for the hypothesis kept)."""
        check = check_motion_screened if self.screened_grading else check_motion

        def grade(i: int) -> HypothesisCheck:
            return check(
                hyp.R[i],
                hyp.t[i],
                K,
                uv1,
                uv2,
                inliers,
                max_reproj_err_px=self.max_reproj_err_px,
                max_cos_parallax=self.max_cos_parallax,
                parallax_rank=self.parallax_rank,
            )

        n = hyp.R.shape[0]
        if not self.parallel_models or n < 2:
            return [grade(i) for i in range(n)]
        half = n // 2
        later = [model_pool().submit(grade, i) for i in range(half, n)]
        return [grade(i) for i in range(half)] + [f.result() for f in later]

    def _result(
        self,
        model: Literal["H", "F"],
        hyp: MotionHypotheses,
        checks: list[HypothesisCheck],
        sel: Selection,
        details: dict[str, Any],
        uv1: F64,
        uv2: F64,
        K: F64,
    ) -> TwoViewResult:
        details["n_good"] = [c.n_good for c in checks]
        details["parallax_deg"] = [c.parallax_deg for c in checks]
        details["hypothesis"] = sel.best
        m = model
        if sel.best is None:
            return TwoViewResult(
                False, f"{m} reconstruction refused: " + "; ".join(sel.failures), model=m, details=details
            )
        best = checks[sel.best]
        xyz_ref = best.xyz_ref
        if self.screened_grading:  # the screened checks leave the points to the hypothesis kept
            xyz_ref = exact_points(hyp.R[sel.best], hyp.t[sel.best], K, uv1, uv2, best.triangulated)
        return TwoViewResult(
            True,
            f"{m} reconstruction: hypothesis {sel.best} with {best.n_good} good points, "
            f"parallax {best.parallax_deg:.3g} deg",
            model=m,
            T_cur_ref=pose_matrix(hyp.R[sel.best], hyp.t[sel.best]),
            xyz_ref=xyz_ref,
            triangulated=best.triangulated,
            details=details,
        )


def _validated(uv_ref_px: Any, uv_cur_px: Any, K: Any, rng: Any) -> tuple[F64, F64, F64]:
    """Check the inputs of ``initialize`` and return them as float64 arrays; ValueError/TypeError naming the argument."""
    out = []
    for name, value in (("uv_ref_px", uv_ref_px), ("uv_cur_px", uv_cur_px)):
        arr = np.asarray(value, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"TwoViewInitializer.initialize: {name} must have shape (M, 2), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"TwoViewInitializer.initialize: {name} contains NaN or inf")
        out.append(arr)
    if out[0].shape != out[1].shape:
        raise ValueError(
            f"TwoViewInitializer.initialize: uv_ref_px and uv_cur_px must have the same shape (one row per "
            f"match), got {out[0].shape} and {out[1].shape}"
        )
    Km = np.asarray(K, dtype=np.float64)
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)):
        raise ValueError(f"TwoViewInitializer.initialize: K must be a finite (3, 3) matrix, got shape {Km.shape}")
    if not (Km[0, 0] > 0 and Km[1, 1] > 0 and np.allclose(Km[2], [0.0, 0.0, 1.0])):
        raise ValueError(
            f"TwoViewInitializer.initialize: K must be a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
            f"with fx, fy > 0, got {Km.tolist()}"
        )
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"TwoViewInitializer.initialize: rng must be a numpy.random.Generator, got {type(rng).__name__}"
        )
    return out[0], out[1], Km
