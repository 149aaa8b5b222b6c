"""SO(3) maps against SciPy's Rotation (an independent implementation) and their defining identities."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from slamkit.geometry import (
    hat,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
    vee,
)

F64 = NDArray[np.float64]
vec3 = arrays(np.float64, 3, elements=st.floats(-10.0, 10.0))
axes = vec3.filter(lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))


@st.composite
def rotation_vectors(draw: st.DrawFn) -> F64:
    """Axis * angle with angles spread over [0, pi), including tiny ones and ones close to pi."""
    axis = draw(axes)
    angle = draw(
        st.one_of(
            st.floats(0.0, 1e-6),
            st.floats(0.0, np.pi - 1e-6),
            st.floats(np.pi - 1e-3, np.pi - 1e-9),
        )
    )
    return np.asarray(axis * angle, dtype=np.float64)


@settings(max_examples=100, deadline=None)
@given(a=vec3, b=vec3)
def test_hat_is_the_cross_product_and_vee_inverts_it(a: F64, b: F64) -> None:
    np.testing.assert_allclose(hat(a) @ b, np.cross(a, b), atol=1e-12)
    np.testing.assert_array_equal(vee(hat(a)), a)
    np.testing.assert_array_equal(hat(a), -hat(a).T)


@settings(max_examples=200, deadline=None)
@given(phi=rotation_vectors())
def test_exp_matches_scipy_and_log_inverts_it(phi: F64) -> None:
    R = so3_exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(so3_log(R), phi, atol=1e-9)


@pytest.mark.parametrize("eps", [0.0, 1e-15, 1e-12, 1e-9, 1e-6])
def test_log_near_pi_recovers_the_rotation(eps: float) -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        R = so3_exp(n * (np.pi - eps))
        phi = so3_log(R)
        assert np.linalg.norm(phi) == pytest.approx(np.pi - eps, abs=1e-12)
        np.testing.assert_allclose(so3_exp(phi), R, atol=1e-14)
        # The axis is +-n; away from exactly pi its sign must be the one of the rotation.
        if eps >= 1e-9:
            np.testing.assert_allclose(phi, n * (np.pi - eps), atol=1e-6)


def test_log_of_identity_and_tiny_rotations() -> None:
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))
    phi = np.array([1e-10, -2e-10, 3e-10])
    np.testing.assert_allclose(so3_log(so3_exp(phi)), phi, rtol=1e-6, atol=0)


def test_batches_match_single_calls() -> None:
    rng = np.random.default_rng(0)
    phis = rng.normal(size=(4, 5, 3))
    Rs = so3_exp(phis)
    assert Rs.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(Rs[2, 3], so3_exp(phis[2, 3]))
    np.testing.assert_allclose(so3_log(Rs), Rotation.from_matrix(Rs.reshape(-1, 3, 3)).as_rotvec().reshape(4, 5, 3))


@settings(max_examples=50, deadline=None)
@given(phi=rotation_vectors(), d=arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)))
def test_jacobians_linearise_the_exponential(phi: F64, d: F64) -> None:
    h = 1e-6
    delta = h * d
    # exp(phi + d) ~ exp(J_l d) exp(phi) ~ exp(phi) exp(J_r d), to second order in |d|.
    target = so3_exp(phi + delta)
    np.testing.assert_allclose(so3_exp(so3_left_jacobian(phi) @ delta) @ so3_exp(phi), target, atol=1e-11)
    np.testing.assert_allclose(so3_exp(phi) @ so3_exp(so3_right_jacobian(phi) @ delta), target, atol=1e-11)
    np.testing.assert_allclose(so3_left_jacobian_inv(phi) @ so3_left_jacobian(phi), np.eye(3), atol=1e-9)
    np.testing.assert_allclose(so3_right_jacobian_inv(phi) @ so3_right_jacobian(phi), np.eye(3), atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(q=arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(lambda q: np.linalg.norm(q) > 1e-3))
def test_quaternions_match_scipy_and_round_trip(q: F64) -> None:
    R = quat_xyzw_to_matrix(q)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-14)
    q2 = matrix_to_quat_xyzw(R)
    expected = q / np.linalg.norm(q) * (1.0 if q[3] >= 0 else -1.0)
    assert q2[3] >= 0 and np.linalg.norm(q2) == pytest.approx(1.0)
    if abs(q[3]) > 1e-9:  # at w = 0, q and -q both have w >= 0
        np.testing.assert_allclose(q2, expected, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(q2), R, atol=1e-14)


def test_quaternion_batches_and_half_turns() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(200, 4))
    R = quat_xyzw_to_matrix(q)
    assert R.shape == (200, 3, 3)
    q2 = matrix_to_quat_xyzw(R)
    assert q2.shape == (200, 4) and np.all(q2[:, 3] >= 0)
    np.testing.assert_allclose(quat_xyzw_to_matrix(q2), R, atol=1e-14)
    # Half turns about each axis (w = 0): the branch that reads x, y or z from the diagonal.
    for axis in range(3):
        R_half = np.diag([-1.0, -1.0, -1.0])
        R_half[axis, axis] = 1.0
        expected = np.zeros(4)
        expected[axis] = 1.0
        np.testing.assert_allclose(np.abs(matrix_to_quat_xyzw(R_half)), expected, atol=1e-15)


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match=r"q: expected finite quaternions with non-zero norm"):
        quat_xyzw_to_matrix(np.zeros(4))
    with pytest.raises(ValueError, match=r"q: expected an array of shape \(4,\) or \(N, 4\)"):
        quat_xyzw_to_matrix(np.ones(3))
    with pytest.raises(ValueError, match=r"phi: expected an array of shape \(3,\)"):
        so3_exp(np.ones(4))
    with pytest.raises(ValueError, match=r"R: expected an array of shape"):
        so3_log(np.eye(4))
