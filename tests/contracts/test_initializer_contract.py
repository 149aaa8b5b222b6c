"""The Initializer contract: every registered map initializer must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("initializer")``, each built from its default config
node. Inputs are two synthetic views (K of the synthetic room: 640x480, f = 470 px) of known points with a known
motion, projected exactly and then with 0.5 px Gaussian noise, some with 10 % planted wrong matches (ORB-SLAM IV).

What an initializer promises (slamkit/interfaces.py Initializer, TwoViewResult):
- on a general scene (points 3-9 m deep) and on a planar one (a floor-like plane 3 m away), with a baseline of 0.6-0.65 m and
  a few degrees of rotation: success, a model ("H" or "F"), T_cur_ref with the true rotation (<= 0.5 deg) and the
  true translation direction (<= 3 deg), and points in the reference frame equal to the truth up to one scale
  (median relative error <= 3 % after the best scale) for at least 90 % of the clean matches, with planted wrong
  matches marked not triangulated (at least 90 % of them);
- the same rng seed gives the same result;
- a pure rotation and a 1 mm baseline are refused (success False) with a non-empty reason, never a wrong map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from slamkit.interfaces import Initializer, TwoViewResult
from slamkit.plugins import ComponentRegistry

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("initializer")]
K = np.array([[470.0, 0.0, 319.5], [0.0, 470.0, 239.5], [0.0, 0.0, 1.0]])
W, H = 640, 480
ROT_DEG, DIR_DEG, POINT_REL_ERR = 0.5, 3.0, 0.03
MIN_TRIANGULATED, MIN_OUTLIERS_REJECTED = 0.9, 0.9


@pytest.fixture(scope="module", params=NAMES)
def initializer(request: pytest.FixtureRequest) -> Initializer:
    built: Initializer = REGISTRY.instantiate("initializer", REGISTRY.get("initializer", request.param).config_node())
    return built


@dataclass(frozen=True)
class TwoViews:
    uv_ref: np.ndarray
    uv_cur: np.ndarray
    xyz_ref: np.ndarray
    T_cur_ref: np.ndarray
    outlier: np.ndarray


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def _project(xyz: np.ndarray) -> np.ndarray:
    p = xyz @ K.T
    return p[:, :2] / p[:, 2:3]


def make_views(
    seed: int,
    scene: str,
    t: tuple[float, float, float],
    rot_deg: float,
    noise_px: float = 0.5,
    outliers: float = 0.0,
    n: int = 300,
) -> TwoViews:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([40, 40], [W - 40, H - 40], size=(4 * n, 2))
    rays = np.c_[(uv - K[:2, 2]) / K[0, 0], np.ones(len(uv))]
    # planar: a tilted plane (a floor seen at 45 deg) 3 m away; general: depths 3-9 m
    normal = np.array([0.0, -1.0, 1.0]) / np.sqrt(2.0)
    depth = 3.0 / (rays @ normal) if scene == "planar" else rng.uniform(3.0, 9.0, len(uv))
    xyz_ref = rays * depth[:, None]
    T = np.eye(4)
    T[:3, :3] = _rotation(np.array([0.2, 1.0, 0.1]), rot_deg)
    T[:3, 3] = t
    xyz_cur = xyz_ref @ T[:3, :3].T + T[:3, 3]
    uv_cur = _project(xyz_cur)
    inside = (xyz_cur[:, 2] > 0) & np.all((uv_cur >= 0) & (uv_cur < [W, H]), axis=1)
    keep = np.flatnonzero(inside)[:n]
    uv_ref = _project(xyz_ref[keep]) + rng.normal(0, noise_px, (keep.size, 2))
    uv_cur = uv_cur[keep] + rng.normal(0, noise_px, (keep.size, 2))
    outlier = np.zeros(keep.size, bool)
    bad = rng.choice(keep.size, int(outliers * keep.size), replace=False)
    outlier[bad] = True
    uv_cur[bad] = rng.uniform([0, 0], [W, H], size=(bad.size, 2))
    return TwoViews(uv_ref, uv_cur, xyz_ref[keep], T, outlier)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def check_recovers(result: TwoViewResult, views: TwoViews) -> None:
    assert result.success, result.reason
    assert result.model in ("H", "F")
    assert result.T_cur_ref is not None and result.xyz_ref is not None and result.triangulated is not None
    T = result.T_cur_ref
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    assert _angle_deg(T[:3, :3].T @ views.T_cur_ref[:3, :3]) <= ROT_DEG
    t_est, t_true = T[:3, 3], views.T_cur_ref[:3, 3]
    cos = t_est @ t_true / (np.linalg.norm(t_est) * np.linalg.norm(t_true))
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) <= DIR_DEG, "translation direction"
    m = views.uv_ref.shape[0]
    assert result.xyz_ref.shape == (m, 3) and result.triangulated.shape == (m,)
    tri = result.triangulated
    assert tri[~views.outlier].mean() >= MIN_TRIANGULATED, f"{tri[~views.outlier].mean():.2f} triangulated"
    if views.outlier.any():
        assert (~tri[views.outlier]).mean() >= MIN_OUTLIERS_REJECTED, "planted wrong matches triangulated"
    good = tri & ~views.outlier
    est, true = result.xyz_ref[good], views.xyz_ref[good]
    assert np.isfinite(est).all()
    scale = np.median(np.linalg.norm(true, axis=1) / np.linalg.norm(est, axis=1))
    assert scale > 0
    rel = np.linalg.norm(est * scale - true, axis=1) / np.linalg.norm(true, axis=1)
    assert np.median(rel) <= POINT_REL_ERR, f"median relative point error {np.median(rel):.4f}"
    # the translation carries the same scale as the points
    assert np.linalg.norm(t_est) * scale == pytest.approx(np.linalg.norm(t_true), rel=0.05)


def check_refused(result: TwoViewResult) -> None:
    assert not result.success, f"accepted with model {result.model}"
    assert isinstance(result.reason, str) and result.reason.strip()


CASES = {
    "general-sideways": dict(scene="general", t=(0.6, 0.05, 0.1), rot_deg=3.0),
    "general-forward-diagonal": dict(scene="general", t=(0.5, -0.1, 0.4), rot_deg=5.0),
    "planar-sideways": dict(scene="planar", t=(0.6, 0.1, 0.0), rot_deg=4.0),
}


def test_is_an_initializer(initializer: Initializer) -> None:
    assert isinstance(initializer, Initializer)


@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
@pytest.mark.parametrize("outliers", [0.0, 0.1], ids=["clean", "10pc-outliers"])
def test_recovers_motion_and_points(initializer: Initializer, case: str, outliers: float) -> None:
    views = make_views(1, outliers=outliers, **CASES[case])  # type: ignore[arg-type]
    result = initializer.initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(0))
    check_recovers(result, views)


def test_same_seed_same_result(initializer: Initializer) -> None:
    views = make_views(2, outliers=0.1, **CASES["general-sideways"])  # type: ignore[arg-type]
    a = initializer.initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(5))
    b = initializer.initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(5))
    assert a.success == b.success and a.model == b.model and a.reason == b.reason
    assert a.T_cur_ref is not None and b.T_cur_ref is not None and np.array_equal(a.T_cur_ref, b.T_cur_ref)
    assert a.xyz_ref is not None and b.xyz_ref is not None
    assert np.array_equal(a.xyz_ref, b.xyz_ref, equal_nan=True)


@pytest.mark.parametrize("scene", ["general", "planar"])
def test_pure_rotation_is_refused(initializer: Initializer, scene: str) -> None:
    views = make_views(3, scene=scene, t=(0.0, 0.0, 0.0), rot_deg=6.0)
    check_refused(initializer.initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(0)))


@pytest.mark.parametrize("scene", ["general", "planar"])
def test_tiny_baseline_is_refused(initializer: Initializer, scene: str) -> None:
    views = make_views(4, scene=scene, t=(0.001, 0.0, 0.0), rot_deg=1.0)
    check_refused(initializer.initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(0)))


# ---- the suite catches a broken initializer --------------------------------------------------------------------


class _Broken:
    """Delegates to a real initializer and spoils its answer."""

    def __init__(self, inner: Initializer, how: str) -> None:
        self.inner, self.how = inner, how

    def initialize(
        self, uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray, rng: np.random.Generator
    ) -> TwoViewResult:
        from dataclasses import replace

        r = self.inner.initialize(uv_ref, uv_cur, K, rng)
        if self.how == "accept-anything":
            return replace(
                r,
                success=True,
                reason="",
                model=r.model or "F",
                T_cur_ref=r.T_cur_ref if r.T_cur_ref is not None else np.eye(4),
            )
        assert r.T_cur_ref is not None and r.xyz_ref is not None
        T = r.T_cur_ref.copy()
        if self.how == "transposed-rotation":
            T[:3, :3] = T[:3, :3].T
            return replace(r, T_cur_ref=T)
        return replace(r, xyz_ref=r.xyz_ref * np.array([1.0, 1.0, 1.1]))  # "stretched-depth"


def test_suite_fails_on_broken_initializers() -> None:
    inner = REGISTRY.instantiate("initializer", REGISTRY.get("initializer", "twoview").config_node())
    views = make_views(1, **CASES["general-sideways"])  # type: ignore[arg-type]
    for how in ("transposed-rotation", "stretched-depth"):
        with pytest.raises(AssertionError):
            check_recovers(
                _Broken(inner, how).initialize(views.uv_ref, views.uv_cur, K, np.random.default_rng(0)), views
            )
    rotation = make_views(3, scene="general", t=(0.0, 0.0, 0.0), rot_deg=6.0)
    with pytest.raises(AssertionError, match="accepted"):
        check_refused(
            _Broken(inner, "accept-anything").initialize(rotation.uv_ref, rotation.uv_cur, K, np.random.default_rng(0))
        )
