"""Homography and fundamental matrix by RANSAC on shared minimal sets, batched over all iterations.

ORB-SLAM sec. IV-2: both models are fitted with the same prefixed number of iterations and the same
8-match minimal sets; each hypothesis is scored with its symmetric transfer errors,
S_M = sum_i rho_M(d_cr^2) + rho_M(d_rc^2) with rho_M(d^2) = Gamma - d^2 if d^2 < T_M else 0 (d^2 in units
of sigma^2). Points are undistorted px; view 1 is the reference, view 2 the current frame, and
H21 / F21 map view 1 to view 2 (x2 ~ H21 x1, x2^T F21 x1 = 0).

"In parallel": ORB-SLAM runs H and F in two threads. Here both run in one vectorised pass instead: each
model is a few batched numpy calls over all iterations (a (B, 2k, 9) SVD, a (B, M, 3) transfer), so a
second thread would only add scheduling on this 2-core target, and one pass keeps the result a pure
function of the drawn sets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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


def _rho(chi2: F64, threshold: float, gamma: float) -> tuple[F64, NDArray[np.bool_]]:
    """Per-entry score contribution Gamma - chi2 where chi2 <= threshold (else 0), and the pass mask.

    NaN/inf chi2 (a degenerate hypothesis) fails the test, as in ORB-SLAM.
    """
    ok = chi2 <= threshold
    return np.where(ok, gamma - chi2, 0.0), ok


def _transfer_sq(H: F64, x_from: F64, x_to: F64) -> F64:
    """H: (B, 3, 3); x_from, x_to: (M, 2) -> (B, M) squared distance between x_to and H x_from (px^2)."""
    # p[b, m] = H[b] @ [x, y, 1]: written out (einsum took 4x as long here, with the same result bit for bit)
    p = x_from[None, :, 0, None] * H[:, None, :, 0] + x_from[None, :, 1, None] * H[:, None, :, 1] + H[:, None, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = p[..., :2] / p[..., 2:3]
    d2: F64 = np.sum((proj - x_to) ** 2, axis=-1)
    return d2


def score_homographies(
    H21: F64, uv1: F64, uv2: F64, sigma_px: float, T_H: float, gamma: float
) -> tuple[F64, NDArray[np.bool_]]:
    """H21: (B, 3, 3); uv1, uv2: (M, 2) px -> (scores S_H (B,), inliers (B, M)).

    As ORB-SLAM's CheckHomography: transfer errors in both images, inlier when both pass T_H.
    """
    inv_s2 = 1.0 / (sigma_px * sigma_px)
    with np.errstate(invalid="ignore", over="ignore"):
        chi_cur = _transfer_sq(H21, uv1, uv2) * inv_s2  # x1 transferred into the current image
        chi_ref = _transfer_sq(adjugate(H21), uv2, uv1) * inv_s2  # x2 transferred back with H12 ~ adj(H21)
        s_cur, ok_cur = _rho(chi_cur, T_H, gamma)
        s_ref, ok_ref = _rho(chi_ref, T_H, gamma)
    scores: F64 = (s_cur + s_ref).sum(axis=1)
    return scores, ok_cur & ok_ref


def score_fundamentals(
    F21: F64, uv1: F64, uv2: F64, sigma_px: float, T_F: float, gamma: float
) -> tuple[F64, NDArray[np.bool_]]:
    """F21: (B, 3, 3); uv1, uv2: (M, 2) px -> (scores S_F (B,), inliers (B, M)).

    As ORB-SLAM's CheckFundamental: point-to-epipolar-line distances in both images tested against T_F,
    scored with Gamma (= T_H, so that both models are scored on the same scale).
    """
    inv_s2 = 1.0 / (sigma_px * sigma_px)
    # epipolar lines in image 2 (F x1) and in image 1 (F^T x2), written out as _transfer_sq's product
    l2 = uv1[None, :, 0, None] * F21[:, None, :, 0] + uv1[None, :, 1, None] * F21[:, None, :, 1] + F21[:, None, :, 2]
    l1 = uv2[None, :, 0, None] * F21[:, None, 0, :] + uv2[None, :, 1, None] * F21[:, None, 1, :] + F21[:, None, 2, :]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        num2 = l2[..., 0] * uv2[:, 0] + l2[..., 1] * uv2[:, 1] + l2[..., 2]
        num1 = l1[..., 0] * uv1[:, 0] + l1[..., 1] * uv1[:, 1] + l1[..., 2]
        chi2 = num2 * num2 / (l2[..., 0] ** 2 + l2[..., 1] ** 2) * inv_s2
        chi1 = num1 * num1 / (l1[..., 0] ** 2 + l1[..., 1] ** 2) * inv_s2
        s2, ok2 = _rho(chi2, T_F, gamma)
        s1, ok1 = _rho(chi1, T_F, gamma)
    scores: F64 = (s1 + s2).sum(axis=1)
    return scores, ok1 & ok2


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
) -> tuple[ModelFit, ModelFit]:
    """RANSAC for H21 and F21 on the same minimal sets -> (best homography, best fundamental matrix).

    uv1, uv2: (M, 2) undistorted px; sets: (B, 8) match indices; h_points_per_set: how many of each
    set's matches the homography DLT uses (4 or 8; the F fit always uses all 8). refine: refit each
    winner on its inliers (``_refit``; not in ORB-SLAM). Each model is estimated in Hartley-normalised
    coordinates and denormalised before scoring in px.
    """
    n1, T1 = hartley_normalization(uv1)
    n2, T2 = hartley_normalization(uv2)
    T2_inv = np.linalg.inv(T2)
    chunk = max(1, _MAX_SCORED_ENTRIES // max(1, uv1.shape[0]))
    best_h: ModelFit | None = None
    best_f: ModelFit | None = None
    for start in range(0, sets.shape[0], chunk):
        idx = sets[start : start + chunk]
        x1, x2 = n1[idx], n2[idx]  # (b, 8, 2)
        H = T2_inv @ homographies_dlt(x1[:, :h_points_per_set], x2[:, :h_points_per_set]) @ T1
        F = T2.T @ fundamentals_8point(x1, x2) @ T1
        s_h, in_h = score_homographies(H, uv1, uv2, sigma_px, T_H, gamma)
        s_f, in_f = score_fundamentals(F, uv1, uv2, sigma_px, T_F, gamma)
        best_h = _best(H, s_h, in_h, start, best_h)
        best_f = _best(F, s_f, in_f, start, best_f)
    assert best_h is not None and best_f is not None  # sets has at least one row (checked by the caller)
    if refine:
        best_h = _refit(best_h, n1, n2, T1, T2, uv1, uv2, sigma_px, T_H, T_F, gamma, "H")
        best_f = _refit(best_f, n1, n2, T1, T2, uv1, uv2, sigma_px, T_H, T_F, gamma, "F")
    return best_h, best_f


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
