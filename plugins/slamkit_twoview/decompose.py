"""Motion hypotheses from a homography (Faugeras & Lustman 1988: 8) and an essential matrix (4).

All rotations/translations are (R21, t21): they map reference-camera points to the current camera,
x_cur = R21 x_ref + t21, with |t21| = 1 (the scale of a two-view reconstruction is arbitrary).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MotionHypotheses:
    """R: (n, 3, 3) rotations; t: (n, 3) unit translations; n_plane: (n, 3) plane normals (H only, else None)."""

    R: F64
    t: F64
    n_plane: F64 | None = None


def homography_singular_values(H21: F64, K: F64) -> F64:
    """(3,) singular values d1 >= d2 >= d3 of the calibrated homography K^-1 H21 K."""
    out: F64 = np.asarray(np.linalg.svd(np.linalg.solve(K, H21 @ K), compute_uv=False), dtype=np.float64)
    return out


def decompose_homography(H21: F64, K: F64) -> MotionHypotheses:
    """The 8 (R, t, n) of Faugeras' decomposition of A = K^-1 H21 K = d R + t n^T.

    With A = U diag(d1, d2, d3) V^T and s = det(U) det(V), A' = diag(d1, d2, d3) = d' R' + t' n'^T where
    R = s U R' V^T, t = U t', n = V n'. Since R' fixes e2, n' = (x1, 0, x3) with
    x1 = e1 sqrt((d1^2 - d2^2) / (d1^2 - d3^2)), x3 = e3 sqrt((d2^2 - d3^2) / (d1^2 - d3^2)), e1, e3 = +-1,
    and d' = +-d2 gives two families of four. The caller must reject nearly equal singular values
    (the decomposition is then undefined: pure rotation or a plane at infinity).
    """
    U, d, Vt = np.linalg.svd(np.linalg.solve(K, H21 @ K))
    d1, d2, d3 = (float(x) for x in d)
    s = float(np.linalg.det(U) * np.linalg.det(Vt))
    den = d1 * d1 - d3 * d3
    a1 = np.sqrt(max(d1 * d1 - d2 * d2, 0.0) / den)
    a3 = np.sqrt(max(d2 * d2 - d3 * d3, 0.0) / den)
    x1 = np.array([a1, a1, -a1, -a1])
    x3 = np.array([a3, -a3, a3, -a3])
    root = np.sqrt(max((d1 * d1 - d2 * d2) * (d2 * d2 - d3 * d3), 0.0))
    sign = np.sign(x1 * x3)  # the sine's sign follows e1 e3

    Rs, ts, ns = [], [], []
    # d' = +d2: R' is a rotation about e2 by theta.
    c_theta = (d2 * d2 + d1 * d3) / ((d1 + d3) * d2)
    s_theta = sign * root / ((d1 + d3) * d2)
    for i in range(4):
        Rp = np.array([[c_theta, 0.0, -s_theta[i]], [0.0, 1.0, 0.0], [s_theta[i], 0.0, c_theta]])
        Rs.append(s * U @ Rp @ Vt)
        ts.append(U @ ((d1 - d3) * np.array([x1[i], 0.0, -x3[i]])))
        ns.append(Vt.T @ np.array([x1[i], 0.0, x3[i]]))
    # d' = -d2: R' is a reflection composed with a rotation (det +1 after the sign flips).
    c_phi = (d1 * d3 - d2 * d2) / ((d1 - d3) * d2)
    s_phi = sign * root / ((d1 - d3) * d2)
    for i in range(4):
        Rp = np.array([[c_phi, 0.0, s_phi[i]], [0.0, -1.0, 0.0], [s_phi[i], 0.0, -c_phi]])
        Rs.append(s * U @ Rp @ Vt)
        ts.append(U @ ((d1 + d3) * np.array([x1[i], 0.0, x3[i]])))
        ns.append(Vt.T @ np.array([x1[i], 0.0, x3[i]]))

    R = np.stack(Rs)
    t = np.stack(ts)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.stack(ns)
    n[n[:, 2] < 0] *= -1.0  # normals facing the camera (sign convention only; not used to select)
    return MotionHypotheses(R, t, n)


def decompose_essential(E21: F64) -> MotionHypotheses:
    """The 4 (R, t) of E21 = [t]x R (Hartley & Zisserman 9.6.2): R in {U W V^T, U W^T V^T}, t = +-u3."""
    U, _, Vt = np.linalg.svd(E21)
    t = U[:, 2] / np.linalg.norm(U[:, 2])
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1 = U @ W @ Vt
    R2 = U @ W.T @ Vt
    R1 = -R1 if np.linalg.det(R1) < 0 else R1  # E is defined up to sign: pick the proper rotation
    R2 = -R2 if np.linalg.det(R2) < 0 else R2
    return MotionHypotheses(np.stack([R1, R2, R1, R2]), np.stack([t, t, -t, -t]))
