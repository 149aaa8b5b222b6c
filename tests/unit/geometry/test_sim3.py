"""Sim3 against the 4x4 matrix exponential (including tiny angles and scales) and the group laws."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from scipy.linalg import expm

from slamkit.geometry import SE3, Sim3, hat, so3_exp

F64 = NDArray[np.float64]


@st.composite
def sim3_twists(draw: st.DrawFn) -> F64:
    """[omega, v, lambda] with |omega| < pi; angles and log-scales drawn from tiny, small and large ranges."""
    axis = draw(arrays(np.float64, 3, elements=st.floats(-1, 1)).filter(lambda a: np.linalg.norm(a) > 1e-3))
    angle = draw(st.one_of(st.just(0.0), st.floats(0, 1e-6), st.floats(0, 0.02), st.floats(0, np.pi - 1e-3)))
    lam = draw(st.one_of(st.just(0.0), st.floats(-1e-6, 1e-6), st.floats(-2.5, 2.5), st.floats(-6.0, 6.0)))
    v = draw(arrays(np.float64, 3, elements=st.floats(-5, 5)))
    return np.r_[axis / np.linalg.norm(axis) * angle, v, lam]


def generator(xi: F64) -> F64:
    G = np.zeros((4, 4))
    G[:3, :3] = hat(xi[:3]) + xi[6] * np.eye(3)
    G[:3, 3] = xi[3:6]
    return G


sims = sim3_twists().map(Sim3.exp)


@settings(max_examples=150, deadline=None)
@given(xi=sim3_twists())
def test_exp_is_the_matrix_exponential_and_log_inverts_it(xi: F64) -> None:
    S = Sim3.exp(xi)
    E = expm(generator(xi))
    np.testing.assert_allclose(S.matrix(), E, rtol=1e-11, atol=1e-11 * np.abs(E).max())
    assert S.s == pytest.approx(np.exp(xi[6]), rel=1e-15)
    np.testing.assert_allclose(S.log(), xi, atol=1e-8)


def test_exp_without_scale_is_se3_exp() -> None:
    xi = np.array([0.1, -0.4, 0.2, 1.0, 2.0, -3.0])
    S = Sim3.exp(np.r_[xi, 0.0])
    np.testing.assert_allclose(S.matrix(), SE3.exp(xi).matrix(), atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(a=sims, b=sims, c=sims, pts=arrays(np.float64, (5, 3), elements=st.floats(-5, 5)))
def test_group_laws_and_action(a: Sim3, b: Sim3, c: Sim3, pts: F64) -> None:
    assert ((a @ b) @ c).allclose(a @ (b @ c), atol=1e-7 * max(1.0, np.abs((a @ b @ c).t).max()))
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(a.inverse().matrix(), np.linalg.inv(a.matrix()), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose((a @ a.inverse()).matrix(), np.eye(4), atol=1e-9)
    np.testing.assert_allclose((a @ b).act(pts), a.act(b.act(pts)), rtol=1e-10, atol=1e-8)
    homog = np.c_[pts, np.ones(5)] @ a.matrix().T
    np.testing.assert_allclose(a.act(pts), homog[:, :3], rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.act(pts[0]), a.act(pts)[0])


@settings(max_examples=100, deadline=None)
@given(S=sims)
def test_from_matrix_recovers_scale_rotation_translation(S: Sim3) -> None:
    assert Sim3.from_matrix(S.matrix()).allclose(S, atol=1e-12 * max(1.0, S.s, np.abs(S.t).max()))


def test_from_matrix_rejects_non_similarities() -> None:
    R = so3_exp(np.array([0.2, 0.3, -0.1]))
    M = np.eye(4)
    M[:3, :3] = np.diag([1.0, 2.0, 1.0]) @ R  # anisotropic scale
    with pytest.raises(ValueError, match=r"S: the 3x3 block is not a similarity s R"):
        Sim3.from_matrix(M)
    M[:3, :3] = -2.0 * R  # det < 0: a reflection
    with pytest.raises(ValueError, match=r"S: the 3x3 block must be s R with s > 0 .* det is -8"):
        Sim3.from_matrix(M)
    M[:3, :3] = 0.0
    with pytest.raises(ValueError, match=r"det is 0"):
        Sim3.from_matrix(M)
    with pytest.raises(ValueError, match=r"Sim3\.s: expected a positive finite scale, got -1\.0"):
        Sim3(-1.0, np.eye(3), np.zeros(3))


def test_se3_conversions() -> None:
    T = SE3.exp(np.array([0.1, 0.2, 0.3, 1.0, -2.0, 0.5]))
    S = Sim3.from_se3(T.matrix(), s=2.5)
    assert S.s == 2.5
    np.testing.assert_array_equal(S.R, T.R)
    np.testing.assert_array_equal(S.t, T.t)
    np.testing.assert_allclose(S.act(np.ones(3)), 2.5 * T.R @ np.ones(3) + T.t)
    # to_se3 keeps R and divides t by s: the rotation and the point sent to the origin are preserved.
    Tr = S.to_se3()
    np.testing.assert_allclose(Tr[:3, :3], T.R)
    np.testing.assert_allclose(Tr[:3, 3], T.t / 2.5)
    centre = -S.R.T @ S.t / S.s
    np.testing.assert_allclose(S.act(centre), np.zeros(3), atol=1e-12)
    np.testing.assert_allclose(SE3.from_matrix(Tr).act(centre), np.zeros(3), atol=1e-12)
    np.testing.assert_allclose(Sim3.from_se3(T.matrix()).to_se3(), T.matrix())
