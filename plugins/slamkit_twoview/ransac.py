"""Homography and fundamental matrix by RANSAC on shared minimal sets, batched over all iterations.

ORB-SLAM sec. IV-2: both models are fitted with the same prefixed number of iterations and the same
8-match minimal sets; each hypothesis is scored with its symmetric transfer errors,
S_M = sum_i rho_M(d_cr^2) + rho_M(d_rc^2) with rho_M(d^2) = Gamma - d^2 if d^2 < T_M else 0 (d^2 in units
of sigma^2). Points are undistorted px; view 1 is the reference, view 2 the current frame, and
H21 / F21 map view 1 to view 2 (x2 ~ H21 x1, x2^T F21 x1 = 0).

"In parallel": ORB-SLAM runs H and F in two threads. Here each model is a few batched numpy calls over all
iterations (a (B, 2k, 9) SVD) and a compiled scoring pass (kernels.py), all GIL-free; with ``parallel`` (the
initializer's ``parallel_models``) F is fitted in a second thread while the caller fits H, as ORB-SLAM does. On
fr1_xyz in real time the second core is free during initialisation (local mapping has no keyframe yet). Either way
the result is a pure function of the drawn sets.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit_twoview.kernels import fundamental_contributions, homography_contributions

F64 = NDArray[np.float64]

# Cap on iterations x matches scored at once: bounds the (chunk, M, 3) temporaries to ~50 MB.
_MAX_SCORED_ENTRIES = 2_000_000
#: Matches in each minimal set: 8 for the 8-point algorithm (ORB-SLAM sec. IV-2).
SET_SIZE = 8
# Rounds of least-squares refit on the inliers (each kept only if the score rises).
_REFIT_ROUNDS = 3


@dataclass(frozen=True)
class ModelFit:
    """The best hypothesis of one model over all RANSAC iterations.

    matrix: (3, 3) H21 or F21 in px (view 1 -> view 2); score: S_H or S_F; inliers: (M,) bool;
    iteration: index of the minimal set that produced it.
    """

    matrix: F64
    score: float
    inliers: NDArray[np.bool_]
    iteration: int


def draw_minimal_sets(n_matches: int, n_iterations: int, set_size: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """(n_iterations, set_size) match indices, distinct within each row, drawn from ``rng`` only."""
    keys = rng.random((n_iterations, n_matches))
    # The set_size smallest random keys of a row are a uniform draw without replacement.
    sets: NDArray[np.int64] = np.argpartition(keys, set_size - 1, axis=1)[:, :set_size].astype(np.int64)
    return sets


def hartley_normalization(uv_px: F64) -> tuple[F64, F64]:
    """uv_px: (M, 2) -> (normalised (M, 2), T (3, 3)) with centroid 0 and mean distance sqrt(2) (Hartley)."""
    centroid = uv_px.mean(axis=0)
    mean_dist = float(np.linalg.norm(uv_px - centroid, axis=1).mean())
    s = np.sqrt(2.0) / mean_dist if mean_dist > 0 else 1.0
    T = np.array([[s, 0.0, -s * centroid[0]], [0.0, s, -s * centroid[1]], [0.0, 0.0, 1.0]])
    return (uv_px - centroid) * s, T


def _null_vectors(A: F64) -> F64:
    """A: (B, r, 9) with r >= 8 -> (B, 9) right singular vectors of the smallest singular value."""
    if A.shape[1] < 9:  # pad with zero rows so that all 9 right singular vectors exist
        A = np.concatenate([A, np.zeros((A.shape[0], 9 - A.shape[1], 9))], axis=1)
    # Thin SVD: only V is needed. The full one also builds the (r, r) U, which for a refit on ~1000 inliers
    # (r = 2000 rows) took ~140 ms per call where this takes well under 1 ms.
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    out: F64 = Vt[:, -1, :]
    return out


def homographies_dlt(x1: F64, x2: F64) -> F64:
    """Batched DLT. x1, x2: (B, k, 2) normalised points, k >= 4 -> (B, 3, 3) H with x2 ~ H x1.

    Each match gives the two rows of x2 x (H x1) = 0; H is the least-squares null vector.
    """
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    zero, one = np.zeros_like(u1), np.ones_like(u1)
    r1 = np.stack([zero, zero, zero, -u1, -v1, -one, v2 * u1, v2 * v1, v2], axis=-1)
    r2 = np.stack([u1, v1, one, zero, zero, zero, -u2 * u1, -u2 * v1, -u2], axis=-1)
    A = np.concatenate([r1, r2], axis=1)  # (B, 2k, 9)
    return _null_vectors(A).reshape(-1, 3, 3)


def fundamentals_8point(x1: F64, x2: F64, weights: F64 | None = None) -> F64:
    """Batched 8-point algorithm. x1, x2: (B, k, 2) normalised, k >= 8; weights: optional (B, k) row
    weights -> (B, 3, 3) rank-2 F with x2^T F x1 = 0."""
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=-1)
    if weights is not None:
        A = A * weights[..., None]
    F = _null_vectors(A).reshape(-1, 3, 3)
    U, S, Vt = np.linalg.svd(F)
    S[:, 2] = 0.0  # rank-2 enforcement: the closest singular matrix in the Frobenius norm
    out: F64 = (U * S[:, None, :]) @ Vt
    return out


def adjugate(M: F64) -> F64:
    """(B, 3, 3) -> (B, 3, 3) adjugate det(M) M^-1: the inverse up to scale, defined even when singular."""
    r0, r1, r2 = M[:, 0], M[:, 1], M[:, 2]
    out: F64 = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)
    return out


def score_homographies(
    H21: F64, uv1: F64, uv2: F64, sigma_px: float, T_H: float, gamma: float
) -> tuple[F64, NDArray[np.bool_]]:
    """H21: (B, 3, 3); uv1, uv2: (M, 2) px -> (scores S_H (B,), inliers (B, M)).

    As ORB-SLAM's CheckHomography: transfer errors in both images, inlier when both pass T_H. Each match's
    contribution is computed by a compiled kernel (kernels.py, the arithmetic of ``_transfer_sq`` and ``_rho``);
    the sum over the matches is numpy's.
    """
    inv_s2 = 1.0 / (sigma_px * sigma_px)
    # x1 transferred into the current image with H21, x2 back with H12 ~ adj(H21)
    contributions, inliers = homography_contributions(
        np.ascontiguousarray(H21, dtype=np.float64),
        np.ascontiguousarray(adjugate(H21), dtype=np.float64),
        np.ascontiguousarray(uv1, dtype=np.float64),
        np.ascontiguousarray(uv2, dtype=np.float64),
        inv_s2,
        float(T_H),
        float(gamma),
    )
    scores: F64 = contributions.sum(axis=1)
    return scores, inliers


def score_fundamentals(
    F21: F64, uv1: F64, uv2: F64, sigma_px: float, T_F: float, gamma: float
) -> tuple[F64, NDArray[np.bool_]]:
    """F21: (B, 3, 3); uv1, uv2: (M, 2) px -> (scores S_F (B,), inliers (B, M)).

    As ORB-SLAM's CheckFundamental: point-to-epipolar-line distances in both images tested against T_F,
    scored with Gamma (= T_H, so that both models are scored on the same scale). Each match's contribution is
    computed by a compiled kernel (kernels.py); the sum over the matches is numpy's.
    """
    inv_s2 = 1.0 / (sigma_px * sigma_px)
    contributions, inliers = fundamental_contributions(
        np.ascontiguousarray(F21, dtype=np.float64),
        np.ascontiguousarray(uv1, dtype=np.float64),
        np.ascontiguousarray(uv2, dtype=np.float64),
        inv_s2,
        float(T_F),
        float(gamma),
    )
    scores: F64 = contributions.sum(axis=1)
    return scores, inliers


def _best(matrices: F64, scores: F64, inliers: NDArray[np.bool_], offset: int, current: ModelFit | None) -> ModelFit:
    """Keep the first hypothesis with the strictly highest score (ORB-SLAM's `currentScore > score`)."""
    i = int(np.argmax(scores))
    if current is None or scores[i] > current.score:
        return ModelFit(matrices[i].copy(), float(scores[i]), inliers[i].copy(), offset + i)
    return current


def fit_models(
    uv1: F64,
    uv2: F64,
    sets: NDArray[np.int64],
    *,
    sigma_px: float,
    T_H: float,
    T_F: float,
    gamma: float,
    h_points_per_set: int,
    refine: bool,
    parallel: bool = False,
) -> tuple[ModelFit, ModelFit]:
    """RANSAC for H21 and F21 on the same minimal sets -> (best homography, best fundamental matrix).

    uv1, uv2: (M, 2) undistorted px; sets: (B, 8) match indices; h_points_per_set: how many of each
    set's matches the homography DLT uses (4 or 8; the F fit always uses all 8). refine: refit each
    winner on its inliers (``_refit``; not in ORB-SLAM). Each model is estimated in Hartley-normalised
    coordinates and denormalised before scoring in px. parallel: F in a second thread while this one does H
    (ORB-SLAM2/3 Initializer: FindHomography and FindFundamental in two std::threads); the batched SVDs and the
    compiled scoring release the GIL. The two models never share state: the result is the same either way.
    """
    n1, T1 = hartley_normalization(uv1)
    n2, T2 = hartley_normalization(uv2)
    T2_inv = np.linalg.inv(T2)
    chunk = max(1, _MAX_SCORED_ENTRIES // max(1, uv1.shape[0]))

    def fit(model: str) -> ModelFit:
        best: ModelFit | None = None
        for start in range(0, sets.shape[0], chunk):
            idx = sets[start : start + chunk]
            x1, x2 = n1[idx], n2[idx]  # (b, 8, 2)
            if model == "H":
                M = T2_inv @ homographies_dlt(x1[:, :h_points_per_set], x2[:, :h_points_per_set]) @ T1
                s, inl = score_homographies(M, uv1, uv2, sigma_px, T_H, gamma)
            else:
                M = T2.T @ fundamentals_8point(x1, x2) @ T1
                s, inl = score_fundamentals(M, uv1, uv2, sigma_px, T_F, gamma)
            best = _best(M, s, inl, start, best)
        assert best is not None  # sets has at least one row (checked by the caller)
        if refine:
            best = _refit(best, n1, n2, T1, T2, uv1, uv2, sigma_px, T_H, T_F, gamma, model)
        return best

    if not parallel:
        return fit("H"), fit("F")
    f_fit = model_pool().submit(fit, "F")
    h_fit = fit("H")
    return h_fit, f_fit.result()


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def model_pool() -> ThreadPoolExecutor:
    """The one worker thread that fits F beside the caller's H, and grades half the motion hypotheses (made at first
    use, shared by every initializer)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(1, thread_name_prefix="twoview-F")
        return _POOL


def _refit(
    fit: ModelFit,
    n1: F64,
    n2: F64,
    T1: F64,
    T2: F64,
    uv1: F64,
    uv2: F64,
    sigma_px: float,
    T_H: float,
    T_F: float,
    gamma: float,
    model: str,
) -> ModelFit:
    """Least-squares re-estimate of a model from all its RANSAC inliers, kept only while it scores higher.

    Not in ORB-SLAM (it leaves refinement to the BA after initialization): the minimal-set model of a
    noisy scene can be degrees off in translation, which then fails the triangulation checks. F is
    refitted with Sampson weights (each row of the 8-point system divided by the gradient norm of
    x2^T F x1 under the previous F), which turns the algebraic error into a first-order geometric one.
    """
    T2_inv = np.linalg.inv(T2)
    for _ in range(_REFIT_ROUNDS):
        idx = np.flatnonzero(fit.inliers)
        if idx.size < SET_SIZE:
            return fit
        x1, x2 = n1[None, idx], n2[None, idx]
        if model == "H":
            M = T2_inv @ homographies_dlt(x1, x2) @ T1
            scores, inliers = score_homographies(M, uv1, uv2, sigma_px, T_H, gamma)
        else:
            Fn = T2_inv.T @ fit.matrix @ np.linalg.inv(T1)  # the current F in normalised coordinates
            M = T2.T @ fundamentals_8point(x1, x2, sampson_weights(Fn, x1[0], x2[0])[None]) @ T1
            scores, inliers = score_fundamentals(M, uv1, uv2, sigma_px, T_F, gamma)
        if not scores[0] > fit.score:
            return fit
        fit = ModelFit(M[0], float(scores[0]), inliers[0], fit.iteration)
    return fit


def sampson_weights(F: F64, x1: F64, x2: F64) -> F64:
    """F: (3, 3); x1, x2: (k, 2) -> (k,) 1 / |grad (x2^T F x1)|, the Sampson weights of the epipolar residuals."""
    l2 = x1 @ F[:, :2].T + F[:, 2]  # F x1
    l1 = x2 @ F[:2, :] + F[2, :]  # F^T x2
    g = np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)
    out: F64 = 1.0 / np.maximum(g, 1e-12 * max(float(g.max(initial=0.0)), 1e-300))
    return out
