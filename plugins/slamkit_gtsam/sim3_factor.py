"""The relative-Sim3 error (ORB-SLAM eq. 10-11) as one vectorised gtsam.CustomFactor over all matches.

GTSAM has no factor for "project a fixed point through a Sim3", and a CustomFactor per match would call Python
once per match per linearization. Here one factor carries every match: its residual is the (4 N,) vector of both
directions' whitened reprojection errors [e1 (2), e2 (2)] per match, computed in numpy, Huber-robustified per
direction (g2o's kernel on chi2, delta^2 = the problem's chi2 gate), and its (4 N, 7) Jacobian is taken by central
differences through GTSAM's own Similarity3 retraction (7 extra vectorised residual evaluations per side), so LM
steps in exactly the chart it differentiates in. With fix_scale the lambda column is zero: LM's damping then
keeps the scale exactly.

Robustification keeps the error and the gradient exact: with c = |e|^2 and rho the Huber cost, the residual is
e sqrt(rho/c) (so 0.5 |r|^2 = 0.5 rho) and the Jacobian J rho' / sqrt(rho/c) (so J^T r = rho' J^T e).
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from slamkit.optim.costs import kannala_brandt_project
from slamkit_gtsam.convert import S_from_similarity3

F64 = NDArray[np.float64]

_STEP = 1e-6  # central-difference step in the tangent (rad, m, log scale): truncation ~1e-12, rounding ~1e-10


class Sim3MatchesResidual:
    """Whitened bidirectional reprojection residuals of fixed matched points under a Sim3 S_12.

    xyz1_c1, xyz2_c2: (N, 3); uv1, uv2: (N, 2) px; inv_sigma1/2: (N,) 1/sigma of each observation (px^-1);
    intrinsics1/2: (4,) fx fy cx cy; delta2: Huber threshold on each direction's chi2 (None = no kernel);
    distortion1/2: (4,) k1..k4 when that keyframe's camera is Kannala-Brandt (its observations raw fisheye pixels,
    ORB-SLAM3's pCamera1 / pCamera2), None for a pinhole one.
    """

    def __init__(
        self,
        xyz1_c1: F64,
        xyz2_c2: F64,
        uv1: F64,
        uv2: F64,
        inv_sigma1: F64,
        inv_sigma2: F64,
        intrinsics1: F64,
        intrinsics2: F64,
        delta2: float | None,
        fix_scale: bool,
        distortion1: F64 | None = None,
        distortion2: F64 | None = None,
    ) -> None:
        self.xyz1 = xyz1_c1
        self.xyz2 = xyz2_c2
        self.uv1 = uv1
        self.uv2 = uv2
        self.w1 = inv_sigma1[:, None]
        self.w2 = inv_sigma2[:, None]
        self.K1 = intrinsics1
        self.K2 = intrinsics2
        self.delta2 = delta2
        self.fix_scale = fix_scale
        self.kb1 = distortion1
        self.kb2 = distortion2

    @staticmethod
    def _project(S: F64, xyz: F64, K: F64, kb: F64 | None = None) -> F64:
        p = xyz @ S[:3, :3].T + S[:3, 3]
        if kb is not None:
            n = len(p)
            u, v = kannala_brandt_project(p, np.broadcast_to(K, (n, 4)), np.broadcast_to(kb, (n, 4)))
            return np.stack([u, v], axis=1)
        z = p[:, 2:3]
        return np.asarray(K[:2] * p[:, :2] / z + K[2:], dtype=np.float64)

    def raw(self, S_12: F64) -> tuple[F64, F64]:
        """(N, 2) whitened errors of direction 1 (uv1 - pi1(S_12 xyz2)) and direction 2 (uv2 - pi2(S_21 xyz1))."""
        S_21 = np.asarray(np.linalg.inv(S_12), dtype=np.float64)
        e1 = (self.uv1 - self._project(S_12, self.xyz2, self.K1, self.kb1)) * self.w1
        e2 = (self.uv2 - self._project(S_21, self.xyz1, self.K2, self.kb2)) * self.w2
        return e1, e2

    def _scales(self, e: F64) -> tuple[F64, F64]:
        """Per-row factors (residual scale sqrt(rho/c), Jacobian scale rho'/sqrt(rho/c)) for whitened errors e."""
        c = (e**2).sum(axis=1)
        if self.delta2 is None:
            one = np.ones(len(e))
            return one, one
        d2 = self.delta2
        outer = c > d2
        cs = np.where(outer, c, 1.0)
        rho_over_c = np.where(outer, (2.0 * np.sqrt(d2 * cs) - d2) / cs, 1.0)
        a = np.sqrt(rho_over_c)
        drho = np.where(outer, np.sqrt(d2 / cs), 1.0)
        return a, drho / a

    def vector(self, S_12: F64) -> F64:
        """(4 N,) raw whitened residuals (no kernel), rows [e1x, e1y, e2x, e2y] per match."""
        e1, e2 = self.raw(S_12)
        return np.concatenate([e1, e2], axis=1).ravel()

    def evaluate(self, g: gtsam.Similarity3, want_jacobian: bool) -> tuple[F64, F64 | None]:
        """Robust residual (4 N,) at g and, when asked, its (4 N, 7) Jacobian in GTSAM's retraction chart."""
        e1, e2 = self.raw(S_from_similarity3(g))
        a1, j1 = self._scales(e1)
        a2, j2 = self._scales(e2)
        r = np.concatenate([e1 * a1[:, None], e2 * a2[:, None]], axis=1).ravel()
        if not want_jacobian:
            return r, None
        n = len(e1)
        J = np.zeros((4 * n, 7))
        dims = 6 if self.fix_scale else 7
        for k in range(dims):
            step = np.zeros(7)
            step[k] = _STEP
            plus = self.vector(S_from_similarity3(g.retract(step)))
            minus = self.vector(S_from_similarity3(g.retract(-step)))
            J[:, k] = (plus - minus) / (2.0 * _STEP)
        row_scale = np.concatenate([np.repeat(j1[:, None], 2, axis=1), np.repeat(j2[:, None], 2, axis=1)], axis=1)
        J *= row_scale.ravel()[:, None]
        return r, J


def make_sim3_factor(key: int, residual: Sim3MatchesResidual) -> gtsam.CustomFactor:
    """A CustomFactor on the Similarity3 at ``key`` whose error is ``residual`` (unit noise: it is pre-whitened)."""
    n = len(residual.xyz1)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[F64] | None) -> F64:
        r, J = residual.evaluate(values.atSimilarity3(this.keys()[0]), H is not None)
        if H is not None and J is not None:
            H[0] = J
        return r

    func: Callable[[gtsam.CustomFactor, gtsam.Values, list[F64] | None], F64] = error
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(4 * n), [key], func)
