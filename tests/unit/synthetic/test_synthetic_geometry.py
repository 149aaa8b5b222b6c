"""Rendered geometry is exact: depth, occlusion, plane coverage, stereo disparity, the planar start."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from slamkit.io.synthetic import SyntheticDataset
from slamkit.io.synthetic.render import RenderOutput

F64 = np.ndarray


def _backproject(ds: SyntheticDataset, depth: np.ndarray, T_w_c: np.ndarray) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) world points of the pixel centres."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    K = ds.camera.K
    x_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    xyz_c = x_c * depth[..., None].astype(np.float64)
    return np.asarray(xyz_c @ T_w_c[:3, :3].T + T_w_c[:3, 3])


def _plane_coords(ds: SyntheticDataset, index: int, xyz_w: np.ndarray) -> tuple[F64, F64, F64]:
    """Signed distance to plane ``index`` (m) and in-plane coordinates along u and v in [0, 1] on it."""
    p = ds.scene.planes[index]
    o, u, v = np.asarray(p.origin_m), np.asarray(p.u_m), np.asarray(p.v_m)
    d = xyz_w - o
    return d @ p.normal, d @ u / (u @ u), d @ v / (v @ v)


@pytest.mark.parametrize("raw_index", [0, 200, 511])
def test_depth_backprojects_onto_the_plane_each_pixel_shows(
    synthetic: Callable[..., SyntheticDataset], raw_index: int
) -> None:
    ds = synthetic(scene="room")
    out = ds.render_raw(raw_index, labels=True)
    assert out.labels is not None
    T = ds.ground_truth.T_w_c[raw_index]
    # A closed room: every pixel sees a surface.
    assert np.all(out.labels >= 0) and np.all(out.depth_m > 0)
    xyz = _backproject(ds, out.depth_m, T)
    for index in np.unique(out.labels):
        mask = out.labels == index
        dist, a, b = _plane_coords(ds, int(index), xyz[mask])
        z = out.depth_m[mask].astype(np.float64)
        # float32 depth: relative error ~6e-8; allow 1e-6 relative.
        assert np.abs(dist).max() <= 1e-6 * z.max() + 1e-9, ds.scene.planes[index].name
        tol = 1e-5
        assert a.min() >= -tol and a.max() <= 1 + tol and b.min() >= -tol and b.max() <= 1 + tol


def _ray_hits(ds: SyntheticDataset, T_w_c: np.ndarray, uv: np.ndarray) -> tuple[F64, F64]:
    """Brute force: nearest front-facing rectangle along each pixel ray; (depth z, plane index)."""
    K = ds.camera.K
    rays_c = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], axis=1)
    rays_w = rays_c @ T_w_c[:3, :3].T
    c = T_w_c[:3, 3]
    best = np.full(len(uv), np.inf)
    label = np.full(len(uv), -1)
    for i, p in enumerate(ds.scene.planes):
        n = p.normal
        if (c - np.asarray(p.origin_m)) @ n <= 0:
            continue
        denom = rays_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            z = ((np.asarray(p.origin_m) - c) @ n) / denom  # ray parameter = camera z (rays have z_c = 1)
        pts = c + z[:, None] * rays_w
        _, a, b = _plane_coords(ds, i, pts)
        hit = (z > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (z < best)
        best[hit], label[hit] = z[hit], i
    return best, label


@pytest.mark.parametrize(("scene", "raw_index"), [("room", 100), ("long_loop", 1500), ("twins", 700)])
def test_zbuffer_matches_brute_force_ray_casting(
    synthetic: Callable[..., SyntheticDataset], scene: str, raw_index: int
) -> None:
    ds = synthetic(scene=scene)
    out = ds.render_raw(raw_index, labels=True)
    assert out.labels is not None
    rng = np.random.default_rng(1)
    uv = np.stack([rng.integers(0, 640, 3000), rng.integers(0, 480, 3000)], axis=1)
    z, label = _ray_hits(ds, ds.ground_truth.T_w_c[raw_index], uv.astype(np.float64))
    rendered = out.depth_m[uv[:, 1], uv[:, 0]].astype(np.float64)
    np.testing.assert_allclose(rendered, z, rtol=1e-6)
    # Labels agree except where two planes meet exactly at the pixel (same depth within float precision).
    agree = out.labels[uv[:, 1], uv[:, 0]] == label
    assert agree.mean() > 0.995


def test_stereo_disparity_is_fx_baseline_over_depth(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="room", stereo=True, baseline_m=0.2)
    assert ds.T_l_r is not None and ds.camera_right is not None
    np.testing.assert_array_equal(ds.T_l_r[:3, 3], [0.2, 0.0, 0.0])
    raw = 300
    T_w_l = ds.ground_truth.T_w_c[raw]
    left = ds.renderer.render(T_w_l, grey=True, labels=True)
    right = ds.renderer.render(T_w_l @ ds.T_l_r, grey=True, labels=True)
    assert left.grey is not None and right.grey is not None
    fx = ds.camera.fx
    v, u = np.mgrid[0:480, 0:640]
    u_r = u - fx * 0.2 / left.depth_m  # rectified: same row, disparity fx b / z
    ok = (u_r >= 1) & (u_r < 638)
    u0 = np.floor(np.where(ok, u_r, 1)).astype(int)
    frac = np.where(ok, u_r, 1) - u0

    def sample(img: np.ndarray, shift: float = 0.0) -> np.ndarray:
        a = np.clip(u0 + int(shift), 0, 639)
        b = np.clip(a + 1, 0, 639)
        return (1 - frac) * img[v, a] + frac * img[v, b]

    assert left.labels is not None and right.labels is not None
    same_surface = ok & (right.labels[v, u0] == left.labels) & (right.labels[v, np.clip(u0 + 1, 0, 639)] == left.labels)
    assert same_surface.mean() > 0.8
    # Depth is the same in both rectified cameras at matching pixels (planes are locally linear in u).
    z_r = sample(right.depth_m.astype(np.float64))
    np.testing.assert_allclose(z_r[same_surface], left.depth_m[same_surface], rtol=2e-3)
    # And the images agree there, much better than at a pixel shifted by a few columns.
    diff = np.abs(sample(right.grey.astype(np.float64)) - left.grey)[same_surface]
    wrong = np.abs(sample(right.grey.astype(np.float64), 4) - left.grey)[same_surface]
    assert np.median(diff) < 3.0 and np.median(wrong) > 5 * max(np.median(diff), 1.0)


def test_planar_start_sees_only_the_facing_wall(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="planar")
    names = {i: p.name for i, p in enumerate(ds.scene.planes)}
    for raw in range(0, 36, 5):  # the first ~1.2 s
        out: RenderOutput = ds.render_raw(raw, labels=True)
        assert out.labels is not None
        seen = {names[int(i)] for i in np.unique(out.labels)}
        assert all(n.startswith("hall/wall_n") for n in seen), seen
        xyz = _backproject(ds, out.depth_m, ds.ground_truth.T_w_c[raw])
        np.testing.assert_allclose(xyz[..., 1], 4.0, atol=1e-5)  # the north wall is the plane y = 4 m


def test_distant_texture_is_mip_mapped_not_aliased(synthetic: Callable[..., SyntheticDataset]) -> None:
    """A far view compared with a 4x supersampled render box-filtered down: mip-mapping keeps them close."""
    ds = synthetic(scene="long_loop")
    from slamkit.io.synthetic.render import PlaneRenderer

    # on the south corridor's centre line, looking east down the corridor (camera z = world +x, y = down)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = (-9.0, -5.7, 1.5)
    out = ds.renderer.render(T, grey=True)
    K4 = ds.camera.K.copy()
    K4[:2] *= 4.0
    K4[:2, 2] += 1.5  # pixel centre (u, v) of the small image is at 4 u + 1.5 in the big one
    big = PlaneRenderer(ds.scene, ds.renderer.bank, K4, 2560, 1920).render(T, grey=True)
    assert out.grey is not None and big.grey is not None
    reference = big.grey.astype(np.float64).reshape(480, 4, 640, 4).mean(axis=(1, 3))
    err = np.abs(out.grey - reference)
    far = out.depth_m > 8.0
    assert far.sum() > 5000
    # Sampling the full-resolution texture (no mip-mapping) differs from the reference by ~39 grey levels
    # on average here (measured); mip-mapping by ~15 (the levels' blur is coarser than the reference's).
    assert np.mean(err[far]) < 22.0
