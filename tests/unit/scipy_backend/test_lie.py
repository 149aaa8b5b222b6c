"""Batched SE3/Sim3 maps of slamkit_scipy.lie against slamkit.geometry's single-transform classes."""

from __future__ import annotations

import numpy as np
import pytest
from slamkit_scipy.lie import (
    se3_exp_batch,
    sim3_ad_batch,
    sim3_adjoint_batch,
    sim3_exp_batch,
    sim3_inverse_batch,
    sim3_log_batch,
)

from slamkit.geometry.se3 import SE3
from slamkit.geometry.sim3 import Sim3


def _tangents(rng: np.random.Generator) -> np.ndarray:
    """Sim3 tangents covering the series branches: tiny and zero angles, |lambda| small, 0 and > 2."""
    xi = rng.normal(0.0, 1.0, (40, 7))
    xi[:5, :3] *= 1e-6  # tiny rotation -> series of W's coefficients
    xi[5:8, :3] = 0.0
    xi[8:12, 6] = 0.0
    xi[12:16, 6] = rng.choice([-3.0, 3.5], 4)  # beyond the series range of the moments
    xi[16:20, :3] *= 1e-3
    xi[16:20, 6] = 2.7
    return xi


def test_sim3_exp_matches_geometry() -> None:
    xi = _tangents(np.random.default_rng(0))
    batch = sim3_exp_batch(xi)
    for k in range(len(xi)):
        np.testing.assert_allclose(batch[k], Sim3.exp(xi[k]).matrix(), rtol=1e-12, atol=1e-12)


def test_sim3_log_inverts_exp_and_matches_geometry() -> None:
    xi = _tangents(np.random.default_rng(1))
    xi[:, :3] *= 0.9  # keep |omega| < pi so log(exp(xi)) == xi
    S = sim3_exp_batch(xi)
    out = sim3_log_batch(S)
    np.testing.assert_allclose(out, xi, rtol=1e-9, atol=1e-10)
    for k in range(len(xi)):
        np.testing.assert_allclose(out[k], Sim3.from_matrix(S[k]).log(), rtol=1e-9, atol=1e-10)


def test_sim3_inverse() -> None:
    S = sim3_exp_batch(_tangents(np.random.default_rng(2)))
    np.testing.assert_allclose(sim3_inverse_batch(S) @ S, np.broadcast_to(np.eye(4), S.shape), atol=1e-10)


def test_se3_exp_matches_geometry() -> None:
    xi = np.random.default_rng(3).normal(0.0, 1.0, (20, 6))
    xi[:3] *= 1e-7
    batch = se3_exp_batch(xi)
    for k in range(len(xi)):
        np.testing.assert_allclose(batch[k], SE3.exp(xi[k]).matrix(), rtol=1e-12, atol=1e-12)


def test_adjoint_moves_a_perturbation_across_the_transform() -> None:
    rng = np.random.default_rng(4)
    S = sim3_exp_batch(rng.normal(0.0, 0.8, (10, 7)))
    xi = rng.normal(0.0, 0.3, (10, 7))
    lhs = S @ sim3_exp_batch(xi) @ sim3_inverse_batch(S)
    rhs = sim3_exp_batch(np.einsum("nij,nj->ni", sim3_adjoint_batch(S), xi))
    np.testing.assert_allclose(lhs, rhs, atol=1e-10)


@pytest.mark.parametrize("seed", [5, 6])
def test_ad_is_the_derivative_of_the_adjoint(seed: int) -> None:
    """d/dt Ad(exp(t x)) y at t = 0 equals ad_x y (the Lie bracket)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, 1.0, (5, 7))
    y = rng.normal(0.0, 1.0, (5, 7))
    h = 1e-6
    num = (
        np.einsum("nij,nj->ni", sim3_adjoint_batch(sim3_exp_batch(h * x)), y)
        - np.einsum("nij,nj->ni", sim3_adjoint_batch(sim3_exp_batch(-h * x)), y)
    ) / (2 * h)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", sim3_ad_batch(x), y), num, atol=1e-7)
