"""SE3 against the 4x4 matrix exponential and GTSAM's Pose3, and the group laws (property-based)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray
from scipy.linalg import expm

from slamkit.geometry import SE3, hat, invert_T, so3_exp, transform_points
from slamkit.geometry.se3 import orthonormalized_T

F64 = NDArray[np.float64]
finite = st.floats(-5.0, 5.0)
# |omega| < pi so that log(exp(xi)) == xi (the log's angle is in [0, pi]).
twists = arrays(np.float64, 6, elements=finite).filter(lambda x: np.linalg.norm(x[:3]) < np.pi - 1e-6)
poses = twists.map(SE3.exp)


def twist_matrix(xi: F64) -> F64:
    G = np.zeros((4, 4))
    G[:3, :3] = hat(xi[:3])
    G[:3, 3] = xi[3:]
    return G


@settings(max_examples=100, deadline=None)
@given(xi=twists)
def test_exp_is_the_matrix_exponential_and_log_inverts_it(xi: F64) -> None:
    T = SE3.exp(xi)
    np.testing.assert_allclose(T.matrix(), expm(twist_matrix(xi)), atol=1e-11)
    np.testing.assert_allclose(T.log(), xi, atol=1e-8)


def test_tangent_order_matches_gtsam_pose3() -> None:
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(4)
    for _ in range(10):
        xi = rng.normal(size=6)
        np.testing.assert_allclose(SE3.exp(xi).matrix(), gtsam.Pose3.Expmap(xi).matrix(), atol=1e-12)
        np.testing.assert_allclose(SE3.exp(xi).adjoint(), gtsam.Pose3.Expmap(xi).AdjointMap(), atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(a=poses, b=poses, c=poses)
def test_group_laws(a: SE3, b: SE3, c: SE3) -> None:
    assert ((a @ b) @ c).allclose(a @ (b @ c), atol=1e-10)
    assert (a @ a.inverse()).allclose(SE3.identity(), atol=1e-12)
    assert (a.inverse() @ a).allclose(SE3.identity(), atol=1e-12)
    assert (a @ SE3.identity()).allclose(a, atol=0)
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    np.testing.assert_allclose(a.inverse().matrix(), np.linalg.inv(a.matrix()), atol=1e-10)


@settings(max_examples=50, deadline=None)
@given(a=poses, b=poses, pts=arrays(np.float64, (7, 3), elements=finite))
def test_act_composes_and_matches_the_matrix(a: SE3, b: SE3, pts: F64) -> None:
    np.testing.assert_allclose((a @ b).act(pts), a.act(b.act(pts)), atol=1e-10)
    homog = np.c_[pts, np.ones(7)] @ a.matrix().T
    np.testing.assert_allclose(a.act(pts), homog[:, :3], atol=1e-12)
    np.testing.assert_allclose(a.act(pts[3]), a.act(pts)[3], atol=1e-12)
    np.testing.assert_allclose(transform_points(a.matrix(), pts), a.act(pts), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(T=poses, xi=twists)
def test_adjoint_moves_twists_between_frames(T: SE3, xi: F64) -> None:
    assert (T @ SE3.exp(xi) @ T.inverse()).allclose(SE3.exp(T.adjoint() @ xi), atol=1e-9)


def test_log_near_half_turn() -> None:
    xi = np.r_[np.array([0.0, 0.0, np.pi - 1e-10]), 1.0, 2.0, 3.0]
    T = SE3.exp(xi)
    assert SE3.exp(T.log()).allclose(T, atol=1e-9)


def test_batch_inverse_and_point_transform() -> None:
    rng = np.random.default_rng(2)
    Ts = np.stack([SE3.exp(rng.normal(size=6)).matrix() for _ in range(12)]).reshape(3, 4, 4, 4)
    np.testing.assert_allclose(invert_T(Ts), np.linalg.inv(Ts), atol=1e-12)
    np.testing.assert_allclose(invert_T(Ts[0, 0]), np.linalg.inv(Ts[0, 0]), atol=1e-12)


def test_is_immutable_and_float64() -> None:
    T = SE3(np.eye(3, dtype=np.float32), np.array([1, 2, 3]))
    assert T.R.dtype == np.float64 and T.t.dtype == np.float64
    with pytest.raises(dataclasses.FrozenInstanceError):
        T.t = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(ValueError):
        T.t[0] = 5.0


def test_rejects_what_is_not_a_rigid_transform() -> None:
    with pytest.raises(ValueError, match=r"SE3\.R: expected a rotation matrix"):
        SE3(2.0 * np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"SE3\.R: expected a rotation matrix .* det = -1"):
        SE3(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    bad_row = np.eye(4)
    bad_row[3, 0] = 0.5
    with pytest.raises(ValueError, match=r"T: expected last row \[0, 0, 0, 1\]"):
        SE3.from_matrix(bad_row)
    with pytest.raises(ValueError, match=r"SE3\.t: expected an array of shape \(3,\), got shape \(4,\)"):
        SE3(np.eye(3), np.zeros(4))
    with pytest.raises(ValueError, match=r"SE3\.t: contains NaN or inf"):
        SE3(np.eye(3), np.array([0.0, np.nan, 0.0]))


def test_from_matrix_orthonormalizes_rounded_rotations() -> None:
    T = SE3.exp(np.array([0.3, -0.2, 0.1, 1.0, 2.0, 3.0])).matrix()
    rounded = np.round(T, 3)  # rotation now off by ~1e-3: rejected as is, accepted when projected
    with pytest.raises(ValueError, match="rotation"):
        SE3.from_matrix(rounded)
    fixed = SE3.from_matrix(rounded, orthonormalize=True)
    np.testing.assert_allclose(fixed.R @ fixed.R.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(fixed.R, T[:3, :3], atol=2e-3)
    np.testing.assert_array_equal(fixed.t, rounded[:3, 3])
    assert SE3.from_matrix(T).allclose(SE3(so3_exp(np.array([0.3, -0.2, 0.1])), T[:3, 3]), atol=0)
    # tracking's shortcut gives the same bits as the checked SE3 round trip
    np.testing.assert_array_equal(orthonormalized_T(rounded), fixed.matrix())
    np.testing.assert_array_equal(orthonormalized_T(T @ T), SE3.from_matrix(T @ T, orthonormalize=True).matrix())
