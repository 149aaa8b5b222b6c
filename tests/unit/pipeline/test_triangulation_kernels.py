"""Local mapping's compiled triangulation tests (slamkit/pipeline/triangulation_kernels.py) decide as the numpy
formulas they replace, the triangulation of a keyframe pair returns what main's numpy path returned (same features,
same points to the bit), and the refresh of new two-keyframe points equals ``refresh_points``."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.so3 import hat
from slamkit.geometry.twoview import triangulate_points
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.config import LocalMappingConfig
from slamkit.pipeline.local_mapping import LocalMapper, _epipole, _fundamental_21, _median
from slamkit.pipeline.map_points import add_observations, add_points, new_pair_points, refresh_new_pairs, refresh_points
from slamkit.pipeline.projection import project_points
from slamkit.pipeline.triangulation_kernels import epipolar_candidates, parallax_ok, triangulated_ok

CAMERA = PinholeCamera(640, 480, 500.0, 505.0, 320.0, 240.0)


def _pose(rng: np.random.Generator, scale: float = 0.3) -> np.ndarray:
    T = np.eye(4)
    a = rng.normal(scale=0.1, size=3)
    T[:3, :3] = np.linalg.qr(np.eye(3) + hat(a))[0] * np.sign(np.diag(np.linalg.qr(np.eye(3) + hat(a))[1]))
    T[:3, 3] = rng.normal(scale=scale, size=3)
    return T


def _keyframe(kf_id: int, T: np.ndarray, uv: np.ndarray, level: np.ndarray, desc: np.ndarray) -> KeyFrame:
    n = uv.shape[0]
    feats = Features(
        uv.astype(np.float32),
        uv.astype(np.float32),
        level.astype(np.int32),
        np.zeros(n, np.float32),
        np.zeros(n, np.float32),
        desc,
        1.2,
        8,
    )
    feats = Observations.monocular(feats, CAMERA.unproject_image(feats.uv_undist_px.astype(np.float64)))
    return KeyFrame(kf_id, kf_id, float(kf_id), T, CAMERA, feats, np.full(n, -1, np.int64))


def _numpy_epipolar(uv1, uv2, F21, sigma2, chi2, epipole, scale2, min_dist2, stereo):  # type: ignore[no-untyped-def]
    """main's numpy form of the epipolar and epipole tests (slamkit.pipeline.local_mapping before the kernels)."""
    lines = np.c_[uv1, np.ones(uv1.shape[0])] @ F21.T
    num = np.einsum("ij,ij->i", lines, np.c_[uv2, np.ones(uv2.shape[0])])
    dist2 = num**2 / np.maximum(lines[:, 0] ** 2 + lines[:, 1] ** 2, 1e-12)
    ok = dist2 < chi2 * sigma2
    with np.errstate(invalid="ignore"):
        near = np.sum((uv2 - epipole) ** 2, axis=1) < min_dist2 * scale2
    return ok & ~(near & ~stereo)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_epipolar_kernel_decides_as_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T1, T2 = _pose(rng), _pose(rng)
    kf1 = _keyframe(0, T1, np.zeros((1, 2)), np.zeros(1), np.zeros((1, 32), np.uint8))
    kf2 = _keyframe(1, T2, np.zeros((1, 2)), np.zeros(1), np.zeros((1, 32), np.uint8))
    F21 = _fundamental_21(kf1, kf2)
    M = 4000
    uv1 = rng.uniform(0, 640, (M, 2))
    # half the candidates on their epipolar line (plus noise), so both outcomes are well represented
    lines = np.c_[uv1, np.ones(M)] @ F21.T
    u2 = rng.uniform(0, 640, M)
    v2 = -(lines[:, 0] * u2 + lines[:, 2]) / lines[:, 1] + rng.normal(scale=2.0, size=M)
    uv2 = np.where(rng.random((M, 1)) < 0.5, np.c_[u2, v2], rng.uniform(0, 480, (M, 2)))
    uv2[:5] = np.nan  # a keypoint without pinhole coordinates (rig bearings behind the camera)
    sigma2 = np.asarray(1.2 ** (2.0 * rng.integers(0, 8, M)), np.float64)
    scale2 = 1.2 ** rng.integers(0, 8, M).astype(np.float64)
    epipole = project_points(T2, (invert_T(T1)[:3, 3])[None], CAMERA)[0][0]
    uv2[5:400] = epipole + rng.normal(scale=8.0, size=(395, 2))  # around the epipole
    stereo = rng.random(M) < 0.1
    expected = _numpy_epipolar(uv1, uv2, F21, sigma2, 3.84, epipole, scale2, 100.0, stereo)
    got = epipolar_candidates(uv1, uv2, F21, sigma2, 3.84, True, epipole, scale2, 100.0, stereo)
    assert 0 < expected.sum() < M
    np.testing.assert_array_equal(got, expected)
    # without the epipole test: the epipolar distance alone
    got_no_epipole = epipolar_candidates(uv1, uv2, F21, sigma2, 3.84, False, epipole, scale2, 100.0, stereo)
    np.testing.assert_array_equal(
        got_no_epipole, _numpy_epipolar(uv1, uv2, F21, sigma2, 3.84, epipole, scale2, 0.0, stereo)
    )
    assert (got_no_epipole & ~got).any()  # the epipole test refused some


@pytest.mark.parametrize("seed", [0, 1])
def test_parallax_and_point_checks_decide_as_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T1, T2 = _pose(rng), _pose(rng)
    M = 3000
    X = rng.normal(size=(M, 3)) * [2.0, 2.0, 1.0] + [0.0, 0.0, 5.0]
    X[:200] *= [1.0, 1.0, -1.0]  # behind
    X[200:260] *= 1e4  # far away: almost parallel rays
    uv1 = project_points(T1, X, CAMERA)[0] + rng.normal(scale=1.5, size=(M, 2))
    uv2 = project_points(T2, X, CAMERA)[0] + rng.normal(scale=1.5, size=(M, 2))
    Kinv = np.asarray(np.linalg.inv(CAMERA.K), np.float64)
    rays1 = (np.c_[uv1, np.ones(M)] @ Kinv.T) @ T1[:3, :3]
    rays2 = (np.c_[uv2, np.ones(M)] @ Kinv.T) @ T2[:3, :3]
    cos_par = np.einsum("ij,ij->i", rays1, rays2) / (np.linalg.norm(rays1, axis=1) * np.linalg.norm(rays2, axis=1))
    expected_par = (cos_par > 0) & (cos_par < 0.9998)
    got_par = parallax_ok(
        uv1, uv2, Kinv, Kinv, np.ascontiguousarray(T1[:3, :3]), np.ascontiguousarray(T2[:3, :3]), 0.9998
    )
    np.testing.assert_array_equal(got_par, expected_par)
    assert 0 < expected_par.sum() < M

    xyz = triangulate_points(T1, T2, CAMERA.K, CAMERA.K, uv1, uv2)
    xyz[:3] = np.nan
    level1, level2 = rng.integers(0, 8, M), rng.integers(0, 8, M)
    s1, s2 = np.asarray(1.2 ** (2.0 * level1), np.float64), np.asarray(1.2 ** (2.0 * level2), np.float64)
    ok = np.all(np.isfinite(xyz), axis=1)
    xyz0 = np.where(np.isfinite(xyz), xyz, 0.0)
    for T, uv, s in ((T1, uv1, s1), (T2, uv2, s2)):
        proj, z, _ = project_points(T, xyz0, CAMERA)
        ok &= z > 0
        ok &= np.sum((np.where(np.isfinite(proj), proj, 1e9) - uv) ** 2, axis=1) < 5.991 * s
    c1, c2 = invert_T(T1)[:3, 3], invert_T(T2)[:3, 3]
    d1, d2 = np.linalg.norm(xyz0 - c1, axis=1), np.linalg.norm(xyz0 - c2, axis=1)
    ok &= (d1 > 0) & (d2 > 0)
    ratio_dist = d2 / np.maximum(d1, 1e-12)
    ratio_octave = 1.2**level1 / 1.2**level2
    factor = 1.5 * 1.2
    ok &= ~((ratio_dist * factor < ratio_octave) | (ratio_dist > ratio_octave * factor))
    intr = np.array([CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy])
    got = triangulated_ok(xyz, uv1, uv2, T1, T2, intr, intr, 5.991 * s1, 5.991 * s2, c1, c2, ratio_octave, factor)
    np.testing.assert_array_equal(got, ok)
    assert 0 < ok.sum() < M


def _scene(seed: int) -> tuple[InMemoryMapStore, KeyFrame, KeyFrame]:
    """Two keyframes seeing 400 common points (random descriptors, levels), in a store, no map points yet."""
    rng = np.random.default_rng(seed)
    T1, T2 = np.eye(4), _pose(rng, 0.2)
    X = rng.normal(size=(400, 3)) * [1.5, 1.0, 0.5] + [0.0, 0.0, 4.0]
    level = rng.integers(0, 3, 400)
    desc = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    desc2 = desc.copy()
    desc2[:, 0] ^= rng.integers(0, 4, 400).astype(np.uint8)  # small Hamming distances
    uv1 = project_points(T1, X, CAMERA)[0] + rng.normal(scale=0.5, size=(400, 2))
    uv2 = project_points(T2, X, CAMERA)[0] + rng.normal(scale=0.5, size=(400, 2))
    store = InMemoryMapStore()
    kf1 = _keyframe(store.new_keyframe_id(), T1, uv1, level, desc)
    kf2 = _keyframe(store.new_keyframe_id(), T2, uv2, level, desc2)
    store.add_keyframe(kf1)
    store.add_keyframe(kf2)
    return store, store.get_keyframe(kf1.id), store.get_keyframe(kf2.id)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pair_triangulation_equals_the_numpy_path(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled path and the numpy path (which stereo keyframes and other cameras keep) match and triangulate the
    same features to the same bits."""
    import slamkit.pipeline.local_mapping as lm

    store, kf1, kf2 = _scene(seed)
    mapper = LocalMapper(LocalMappingConfig(), Atlas.of(store), None)  # type: ignore[arg-type]
    i1, i2 = mapper._match_for_triangulation(kf1, kf2)
    compiled = mapper._triangulate(kf1, kf2, i1, i2)
    assert i1.size > 100 and compiled is not None and compiled[0].size > 100
    monkeypatch.setattr(lm, "_pinhole_one_camera", lambda kf: False)
    numpy_path = mapper._triangulate(kf1, kf2, i1, i2)
    assert numpy_path is not None
    for got, expected in zip(compiled, numpy_path, strict=True):
        assert got.dtype == expected.dtype and got.tobytes() == expected.tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_refresh_of_new_pairs_equals_refresh_points(seed: int) -> None:
    store, kf1, kf2 = _scene(seed)
    rng = np.random.default_rng(seed + 10)
    feats = rng.permutation(400)[:150]
    f1, f2 = feats, rng.permutation(400)[:150]
    ids = []
    for a, b in zip(f1.tolist(), f2.tolist(), strict=True):
        pid = store.new_point_id()
        store.add_point(
            MapPoint(pid, rng.normal(size=3) + np.array([0, 0, 4.0]), kf2.features.descriptors[b], kf2.id, kf2.id)
        )
        store.add_observation(pid, kf2.id, b)
        store.add_observation(pid, kf1.id, a)
        ids.append(pid)
    names = ("normal_w", "d_min_m", "d_max_m", "descriptor")
    ids_a = np.array(ids, np.int64)
    # new points referenced to kf2 (the keyframe triangulating): kf2 plays kf1's part, the ids are in both orders
    for first, ff, second, fs in ((kf2, f2, kf1, f1), (kf1, f1, kf2, f2)):
        for pid in ids:  # the reference keyframe of the refresh
            store._points[pid].__dict__["ref_kf_id"] = first.id
        refresh_points(store, ids)
        expected = {n: store.point_rows(ids_a, n).copy() for n in names}
        for n in names:  # forget the values
            store.assign_points(ids_a, n, np.zeros_like(expected[n]))
        refresh_new_pairs(store, ids_a, first, ff, second, fs)
        for n in names:
            np.testing.assert_array_equal(store.point_rows(ids_a, n), expected[n], err_msg=n)
        assert np.isfinite(expected["d_max_m"]).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_new_pair_points_are_the_refreshed_points(seed: int) -> None:
    """Points made by new_pair_points and then observed are, attribute for attribute and in the map's table, the
    points made bare, observed, and refreshed by refresh_new_pairs (local mapping's former order), for either
    keyframe as the reference."""
    for ref in (0, 1):
        maps = []
        for folded in (False, True):
            store, kf_a, kf_b = _scene(seed)
            kf1, kf2 = (kf_a, kf_b) if ref == 0 else (kf_b, kf_a)
            rng = np.random.default_rng(seed + 20)
            f1, f2 = rng.permutation(400)[:120], rng.permutation(400)[:120]
            xyz = rng.normal(size=(120, 3)) + np.array([0, 0, 4.0])
            ids = np.array([store.new_point_id() for _ in range(120)], np.int64)
            if folded:
                add_points(store, new_pair_points(ids, xyz, kf1, f1, kf2, f2))
            else:
                for pid, p, a in zip(ids.tolist(), xyz, f1.tolist(), strict=True):
                    store.add_point(MapPoint(pid, p, kf1.features.descriptors[a], kf1.id, kf1.id))
            add_observations(store, ids, kf1.id, f1)
            add_observations(store, ids, kf2.id, f2)
            if not folded:
                refresh_new_pairs(store, ids, kf1, f1, kf2, f2)
            maps.append((store, ids))
        (old, ids), (new, _) = maps
        for name in ("xyz_w", "normal_w", "d_min_m", "d_max_m", "descriptor", "n_observations", "n_visible"):
            a, b = old.point_rows(ids, name), new.point_rows(ids, name)
            assert a.tobytes() == b.tobytes(), name
        for pid in ids.tolist():
            p, q = old.get_point(pid), new.get_point(pid)
            for name in ("xyz_w", "normal_w", "descriptor"):
                assert getattr(p, name).tobytes() == getattr(q, name).tobytes(), name
            assert (p.d_min_m, p.d_max_m, p.ref_kf_id, p.first_kf_id) == (
                q.d_min_m,
                q.d_max_m,
                q.ref_kf_id,
                q.first_kf_id,
            )
            assert list(p.observations.items()) == list(q.observations.items())
        assert np.isfinite(new.point_rows(ids, "d_max_m")).all()


def test_median_is_numpys_median_to_the_bit() -> None:
    """``_median`` (one partition) gives np.median's float for odd and even sizes, ties, infinities and NaN."""
    rng = np.random.default_rng(3)
    for n in [*range(1, 40), 101, 200, 999, 1000]:
        for r in range(12):
            values = rng.normal(2.0, 1.0, n) * (1e-3, 1.0, 1e3)[r % 3]
            if r % 4 == 1:
                values[rng.integers(n)] = values[rng.integers(n)]
            if r % 5 == 2:
                values[rng.integers(n)] = np.nan
            if r % 6 == 3:
                values[rng.integers(n)] = np.inf
            with np.errstate(invalid="ignore"):
                expected = float(np.median(values))
                got = _median(values)
            assert got == expected or (np.isnan(got) and np.isnan(expected)), (n, r)


def test_epipole_is_project_points_to_the_bit() -> None:
    """``_epipole``: the centre of kf1 projected into kf2 as ``project_points`` does, for random poses (a centre
    behind the camera included)."""
    rng = np.random.default_rng(4)
    uv, level, desc = rng.uniform(0, 480, (5, 2)), np.zeros(5), rng.integers(0, 256, (5, 32), dtype=np.uint8)
    for _ in range(200):
        kf1 = _keyframe(0, _pose(rng, 2.0), uv, level, desc)
        kf2 = _keyframe(1, _pose(rng, 2.0), uv, level, desc)
        expected = project_points(kf2.T_c_w, kf1.center_w[None], kf2.camera)[0][0]
        assert _epipole(kf1, kf2).tobytes() == expected.tobytes()
