"""Huber kernel on chi-square values, as g2o's RobustKernelHuber applies it (ORB-SLAM's optimizers).

For a residual r with information Omega, chi2 = r^T Omega r. The robust cost is rho(chi2) with
rho(c) = c for c <= delta^2 and 2 delta sqrt(c) - delta^2 beyond; iteratively reweighted least squares
scales the information by rho'(c) = min(1, delta / sqrt(c)). Costs are in whitened px^2 (g2o's chi2;
GTSAM's error is half of it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def huber_cost(chi2: F64, delta: F64 | float) -> F64:
    """chi2: (N,) >= 0; delta: (N,) or scalar Huber threshold on the whitened norm -> (N,) rho(chi2)."""
    d2 = np.asarray(delta) ** 2
    out: F64 = np.where(chi2 <= d2, chi2, 2.0 * np.asarray(delta) * np.sqrt(chi2) - d2)
    return out


def huber_weight(chi2: F64, delta: F64 | float) -> F64:
    """(N,) IRLS weight rho'(chi2) = 1 inside the threshold, delta / sqrt(chi2) outside (in (0, 1])."""
    out: F64 = np.minimum(1.0, np.asarray(delta) / np.sqrt(np.maximum(chi2, 1e-300)))
    return out


def inv_sigma2(level: NDArray[np.int64], scale_factor: float) -> F64:
    """(N,) information 1 / sigma^2 with sigma^2 = scale_factor^(2 level) (ORB-SLAM's mvInvLevelSigma2)."""
    out: F64 = float(scale_factor) ** (-2.0 * level.astype(np.float64))
    return out
