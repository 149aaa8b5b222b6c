"""The compiled retraction se3_exp_times (shared by tracking's pose optimization and the scipy bundle adjustment)
against the 4x4 matrix exponential, on both sides of its small-angle series switch."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.linalg import expm

from slamkit.geometry import SE3, hat
from slamkit.geometry.se3_kernels import se3_exp_times
from slamkit.geometry.so3 import _SMALL_ANGLE

F64 = NDArray[np.float64]

# Rotation angles (rad) from 0 through the series/closed-form switch (so3._SMALL_ANGLE = 1e-4) to nearly pi.
ANGLES = [
    0.0,
    1e-12,
    1e-8,
    1e-6,
    1e-5,
    0.5 * _SMALL_ANGLE,
    0.999 * _SMALL_ANGLE,
    _SMALL_ANGLE,
    1.001 * _SMALL_ANGLE,
    1.5 * _SMALL_ANGLE,
    3e-4,
    1e-3,
    1e-2,
    0.1,
    1.0,
    3.0,
]


def twist_matrix(xi: F64) -> F64:
    """xi (6,) [omega, v] -> (4, 4) [[hat(omega), v], [0, 0]], whose matrix exponential is exp(xi)."""
    G = np.zeros((4, 4))
    G[:3, :3] = hat(xi[:3])
    G[:3, 3] = xi[3:]
    return G


def _twist(rng: np.random.Generator, angle: float, v_norm: float) -> F64:
    axis = rng.normal(size=3)
    v = rng.normal(size=3)
    return np.concatenate([axis / np.linalg.norm(axis) * angle, v / np.linalg.norm(v) * v_norm])


EPS = float(np.finfo(np.float64).eps)


def kernel_angle(xi: F64) -> float:
    """|omega| as se3_exp_times computes it (the side of the switch it takes)."""
    return float(np.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2]))


def translation_tolerance(angle: float, v_norm: float) -> float:
    """Bound on |t - t_expm| (m): a few ulps of |v|, plus, with the closed forms (angle >= the switch), the
    cancellation of b = (1 - cos theta) / theta^2 (cos rounded to ~eps/2) times |W v| = theta |v|."""
    closed_form = EPS / (2.0 * angle) if angle >= _SMALL_ANGLE else 0.0
    return (8.0 * EPS + closed_form) * v_norm


@pytest.mark.parametrize("angle", ANGLES)
@pytest.mark.parametrize("v_norm", [0.0, 1e-3, 1.0, 10.0])
def test_exp_times_is_the_matrix_exponential(angle: float, v_norm: float) -> None:
    """exp(xi) I == expm(twist matrix): the rotation block to a few ulps whatever side of the switch the angle is
    on, the translation within translation_tolerance; the rotation is orthonormal and the last row [0, 0, 0, 1]."""
    rng = np.random.default_rng(int(angle * 1e12) % 2**32 + int(v_norm * 1e3))
    for _ in range(20):
        xi = _twist(rng, angle, v_norm)
        got = se3_exp_times(xi, np.eye(4))
        want = expm(twist_matrix(xi))
        np.testing.assert_allclose(got[:3, :3], want[:3, :3], rtol=0.0, atol=16 * EPS)
        np.testing.assert_allclose(
            got[:3, 3], want[:3, 3], rtol=0.0, atol=translation_tolerance(kernel_angle(xi), v_norm)
        )
        np.testing.assert_allclose(got[:3, :3] @ got[:3, :3].T, np.eye(3), rtol=0.0, atol=4 * EPS)
        assert np.array_equal(got[3], [0.0, 0.0, 0.0, 1.0])


def test_the_series_is_exact_below_the_switch() -> None:
    """Below the switch the series leaves no cancellation: the translation is within a few ulps of |v| where the
    closed forms (one step above the switch) are allowed, and do show, hundreds of ulps."""
    rng = np.random.default_rng(3)
    below = above = 0.0
    for _ in range(200):
        xi = _twist(rng, 1.0, 1.0)
        lo, hi = xi.copy(), xi.copy()
        lo[:3] *= 0.999 * _SMALL_ANGLE
        hi[:3] *= 1.5 * _SMALL_ANGLE
        assert kernel_angle(lo) < _SMALL_ANGLE < kernel_angle(hi)
        below = max(below, float(np.abs(se3_exp_times(lo, np.eye(4)) - expm(twist_matrix(lo))).max()))
        above = max(above, float(np.abs(se3_exp_times(hi, np.eye(4)) - expm(twist_matrix(hi))).max()))
    assert below <= 8 * EPS
    assert 50 * EPS < above <= translation_tolerance(1.5 * _SMALL_ANGLE, 1.0)


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.999 * _SMALL_ANGLE, _SMALL_ANGLE, 0.2, 2.5])
def test_exp_times_left_multiplies(angle: float) -> None:
    """se3_exp_times(xi, T) is exp(xi) @ T (left perturbation, xi in the frame T maps into) with
    slamkit.geometry.se3.SE3.exp as exp; its inputs are not written."""
    rng = np.random.default_rng(11)
    xi = _twist(rng, angle, 0.3)
    T = SE3.exp(rng.normal(size=6)).matrix()
    T[:3, 3] *= 50.0  # poses far from the origin, as on KITTI
    xi0, T0 = xi.copy(), T.copy()
    got = se3_exp_times(xi, T)
    np.testing.assert_allclose(got, SE3.exp(xi).matrix() @ T, rtol=0.0, atol=64 * EPS * 50.0)
    np.testing.assert_allclose(got, expm(twist_matrix(xi)) @ T, rtol=0.0, atol=64 * EPS * 50.0)
    assert not np.allclose(got, T) or angle == 0.0
    assert np.array_equal(xi, xi0) and np.array_equal(T, T0)
