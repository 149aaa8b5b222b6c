"""The LM driver's initial damping from a callable max diag(H) (read at the first linearization only), and the bundle
solver's pinhole stages without the per-observation camera array: the same results to the bit as the eager forms."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import slamkit_scipy.bundle as bundle
from slamkit_scipy.lm import LMSettings, levenberg_marquardt

from slamkit.optim import synthetic as syn

F64 = np.ndarray


_T = np.linspace(0.0, 1.0, 30)
_Y = 2.0 * np.exp(-1.3 * _T) + 0.01 * np.sin(17 * _T)


class _CurveFit:
    """LM callables of the least squares fit of y = a exp(b t) (x = (a, b)); linearize gives max diag(H) as a float
    or as a callable that counts its calls."""

    def __init__(self, hmax_callable: bool) -> None:
        self.hmax_callable = hmax_callable
        self.calls = 0
        self.g = np.zeros(2)

    def linearize(self, x: F64) -> tuple[F64, F64, float, Any]:
        e = np.exp(x[1] * _T)
        r = x[0] * e - _Y
        J = np.c_[e, x[0] * _T * e]
        H = J.T @ J
        self.g = J.T @ r
        value = float(np.max(np.diag(H)))

        def hmax() -> float:
            self.calls += 1
            return value

        return H, self.g, float(r @ r), hmax if self.hmax_callable else value

    def solve(self, H: F64, lam: float) -> F64:
        return np.asarray(np.linalg.solve(H + lam * np.eye(2), -self.g), np.float64)

    @staticmethod
    def cost(x: F64) -> float:
        r = x[0] * np.exp(x[1] * _T) - _Y
        return float(r @ r)


@pytest.mark.parametrize("lambda_init", [None, 1e-3])
def test_callable_hmax_is_the_float_and_is_read_once(lambda_init: float | None) -> None:
    fits = [_CurveFit(False), _CurveFit(True)]
    eager, lazy = (
        levenberg_marquardt(
            np.array([1.0, 0.0]),
            f.linearize,
            f.solve,
            lambda x, h: x + h,
            f.cost,
            15,
            LMSettings(lambda_init=lambda_init),
        )
        for f in fits
    )
    assert eager.iterations == lazy.iterations > 3
    assert np.array_equal(eager.x, lazy.x) and eager.cost_final == lazy.cost_final
    assert fits[1].calls == (0 if lambda_init is not None else 1)  # read at the first linearization only


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.4])
def test_bundle_lazy_hmax_and_no_pinhole_camera_array_change_no_bit(
    monkeypatch: pytest.MonkeyPatch, stereo_ratio: float
) -> None:
    problem, _ = syn.make_bundle_problem(
        np.random.default_rng(31), n_free=4, n_fixed=3, n_points=300, n_obs=1600, stereo_ratio=stereo_ratio
    )
    new = bundle.bundle_adjust(problem, LMSettings())
    stage_init = bundle._Stage.__init__
    linearize = bundle.BundleSolver.linearize

    def eager_stage(self: bundle._Stage, *args: Any, **kwargs: Any) -> None:
        stage_init(self, *args, **kwargs)
        assert self.cam.shape == (0, 8)  # a pinhole problem: no camera array
        self.cam = self.obs.cam()  # the former (E, 8) array

    def eager_linearize(self: bundle.BundleSolver, state: bundle.BAState) -> tuple[Any, F64, float, float]:
        system, g, f, hmax = linearize(self, state)
        return system, g, f, hmax()

    monkeypatch.setattr(bundle._Stage, "__init__", eager_stage)
    monkeypatch.setattr(bundle.BundleSolver, "linearize", eager_linearize)
    old = bundle.bundle_adjust(problem, LMSettings())
    assert new.iterations == old.iterations > 2
    assert np.array_equal(new.T_c_w, old.T_c_w) and np.array_equal(new.xyz_w, old.xyz_w)
    assert np.array_equal(new.outlier, old.outlier) and new.cost_final == old.cost_final
