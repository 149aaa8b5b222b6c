"""Sim3 RANSAC recovers a known similarity from matched 3D points with outliers."""

from __future__ import annotations

import numpy as np

from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.sim3_ransac import ransac_sim3
from slamkit.geometry.so3 import so3_exp

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def project(xyz: np.ndarray) -> np.ndarray:
    return (xyz[:, :2] / xyz[:, 2:]) * 500.0 + np.array([320.0, 240.0])


def make(rng: np.random.Generator, n: int, outlier_ratio: float, s: float) -> tuple:
    S_12 = Sim3(s, so3_exp(np.array([0.05, -0.1, 0.03])), np.array([0.2, -0.1, 0.3]))
    xyz2 = rng.uniform([-2, -1.5, 3], [2, 1.5, 8], (n, 3))
    xyz1 = S_12.act(xyz2)
    uv1, uv2 = project(xyz1) + rng.normal(0, 0.5, (n, 2)), project(xyz2) + rng.normal(0, 0.5, (n, 2))
    bad = rng.random(n) < outlier_ratio
    xyz2[bad] = rng.uniform([-2, -1.5, 3], [2, 1.5, 8], (int(bad.sum()), 3))  # wrong 3D match
    return S_12, xyz1, xyz2, uv1, uv2, bad


def test_recovers_scale_rotation_translation_and_flags_outliers() -> None:
    rng = np.random.default_rng(0)
    S_true, xyz1, xyz2, uv1, uv2, bad = make(rng, 200, 0.3, 1.7)
    sig = np.ones(200)
    res = ransac_sim3(xyz1, xyz2, uv1, uv2, K, K, sig, sig, np.random.default_rng(1))
    assert res.S_12 is not None
    assert abs(res.S_12.s - 1.7) < 0.01
    assert np.abs(res.S_12.R - S_true.R).max() < 5e-3
    assert np.linalg.norm(res.S_12.t - S_true.t) < 0.05
    assert not np.any(res.inliers & bad)
    assert res.inliers[~bad].mean() > 0.9


def test_fix_scale_and_refusal() -> None:
    rng = np.random.default_rng(2)
    _, xyz1, xyz2, uv1, uv2, _ = make(rng, 100, 0.0, 1.0)
    sig = np.ones(100)
    res = ransac_sim3(xyz1, xyz2, uv1, uv2, K, K, sig, sig, np.random.default_rng(3), fix_scale=True)
    assert res.S_12 is not None and res.S_12.s == 1.0
    # unrelated point sets: no hypothesis reaches 20 inliers
    junk = rng.uniform([-2, -1.5, 3], [2, 1.5, 8], (100, 3))
    res = ransac_sim3(xyz1, junk, uv1, project(junk), K, K, sig, sig, np.random.default_rng(4))
    assert res.S_12 is None
