"""Umeyama and Horn alignment: exact recovery, agreement with each other and with evo, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray

from slamkit.geometry import Sim3, horn_alignment, umeyama_alignment

F64 = NDArray[np.float64]
METHODS = [umeyama_alignment, horn_alignment]


@st.composite
def transforms(draw: st.DrawFn) -> Sim3:
    omega = draw(arrays(np.float64, 3, elements=st.floats(-3.0, 3.0)).filter(lambda w: np.linalg.norm(w) < 3.1))
    t = draw(arrays(np.float64, 3, elements=st.floats(-100.0, 100.0)))
    lam = draw(st.floats(-3.0, 3.0))
    return Sim3.exp(np.r_[omega, t, lam])


def cloud(seed: int, n: int = 40) -> F64:
    return np.random.default_rng(seed).normal(scale=[3.0, 2.0, 1.0], size=(n, 3))


@pytest.mark.parametrize("align", METHODS)
@settings(max_examples=50, deadline=None)
@given(S=transforms(), seed=st.integers(0, 2**32 - 1), n=st.integers(3, 60))
def test_recovers_a_similarity_exactly(align: object, S: Sim3, seed: int, n: int) -> None:
    src = cloud(seed, n)
    est = align(src, S.act(src), True)  # type: ignore[operator]
    assert est.s == pytest.approx(S.s, rel=1e-9)
    np.testing.assert_allclose(est.R, S.R, atol=1e-9)
    np.testing.assert_allclose(est.t, S.t, atol=1e-8 * max(1.0, np.abs(S.t).max()))


@pytest.mark.parametrize("align", METHODS)
@settings(max_examples=30, deadline=None)
@given(S=transforms(), seed=st.integers(0, 2**32 - 1))
def test_recovers_a_rigid_transform_without_scale(align: object, S: Sim3, seed: int) -> None:
    src = cloud(seed)
    rigid = Sim3(1.0, S.R, S.t)
    est = align(src, rigid.act(src), False)  # type: ignore[operator]
    assert est.s == 1.0
    assert est.allclose(rigid, atol=1e-8)


@pytest.mark.parametrize("align", METHODS)
def test_planar_points_are_enough(align: object) -> None:
    src = np.c_[np.random.default_rng(0).normal(size=(10, 2)), np.zeros(10)]
    S = Sim3.exp(np.array([0.3, -1.0, 2.0, 1.0, 2.0, 3.0, 0.4]))
    assert align(src, S.act(src), True).allclose(S, atol=1e-9)  # type: ignore[operator]


def test_methods_agree_on_noisy_data() -> None:
    rng = np.random.default_rng(5)
    S = Sim3.exp(np.array([0.4, -0.2, 1.1, 3.0, -1.0, 2.0, 0.7]))
    src = cloud(1, 200)
    dst = S.act(src) + rng.normal(scale=0.02, size=src.shape)
    u = umeyama_alignment(src, dst, True)
    h = horn_alignment(src, dst, True)
    # Both rotations are the least-squares optimum of the same cross-covariance.
    np.testing.assert_allclose(u.R, h.R, atol=1e-10)
    # The scales (least-squares vs Horn's symmetric ratio of spreads) differ by O(noise^2 / spread^2).
    assert u.s == pytest.approx(h.s, rel=1e-3)
    assert u.s == pytest.approx(S.s, rel=5e-3)
    np.testing.assert_allclose(u.act(src), h.act(src), atol=0.01)

    # Umeyama's scale is the least-squares one: no other scale with the same R fits better.
    def cost(s: float) -> float:
        t = dst.mean(0) - s * u.R @ src.mean(0)
        return float(np.sum((dst - (s * src @ u.R.T + t)) ** 2))

    assert cost(u.s) <= cost(h.s)
    assert cost(u.s) <= min(cost(u.s * 1.001), cost(u.s / 1.001))


def test_umeyama_matches_evo() -> None:
    evo_geometry = pytest.importorskip("evo.core.geometry")
    rng = np.random.default_rng(8)
    S = Sim3.exp(np.array([-0.4, 0.9, 0.2, 1.0, 2.0, -3.0, -0.5]))
    src = cloud(2, 100)
    dst = S.act(src) + rng.normal(scale=0.05, size=src.shape)
    for with_scale in (True, False):
        R, t, s = evo_geometry.umeyama_alignment(src.T, dst.T, with_scale)
        est = umeyama_alignment(src, dst, with_scale)
        np.testing.assert_allclose(est.R, R, atol=1e-12)
        np.testing.assert_allclose(est.t, t, atol=1e-12)
        assert est.s == pytest.approx(s, rel=1e-12)


@pytest.mark.parametrize("align", METHODS)
def test_degenerate_input_raises_a_clear_error(align: object) -> None:
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    good = cloud(0, 5)
    cases = [
        (good[:2], good[:2], "at least 3 point pairs, got 2"),
        (line, good, "src: the points are degenerate"),
        (good, line, "dst: the points are degenerate"),
        (np.ones((5, 3)), good, "src: the points are degenerate"),
        (good, good[:4], "expected the same number of points, got 5 and 4"),
        (good[:, :2], good, r"src: expected an array of shape \(N, 3\)"),
        (np.where(good > 1, np.nan, good), good, "src: contains NaN or inf"),
    ]
    for src, dst, message in cases:
        with pytest.raises(ValueError, match=message):
            align(src, dst, True)  # type: ignore[operator]
