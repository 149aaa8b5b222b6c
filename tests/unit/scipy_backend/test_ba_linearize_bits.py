"""slamkit_scipy.kernels.ba_linearize against its former loops (the pose Jacobian formed for every observation, W
zeroed up front, each block summed by _accumulate_block's loop over a run-time row count), compiled here with the
same flags: every returned array and the cost must be equal to the bit, for pinhole (mono and stereo rows), fisheye,
robust and plain weights, and fixed poses and points."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import pytest
from slamkit_scipy.kernels import _accumulate_block, ba_linearize

from slamkit.optim.kannala_brandt import kb_jacobian, kb_project

F64 = np.ndarray


@numba.njit(nogil=True, fastmath={"contract"})
def _former_linearize(  # type: ignore[no-untyped-def]
    R, t, X, obs_pose, obs_point, c, p, uvr, stereo, intr, bf, info, delta, robust, nc, npt, cam, fisheye
):
    """ba_linearize as it was before its rows were written out (slamkit 5f78dd9), term for term."""
    E = obs_pose.shape[0]
    U = np.zeros((nc, 6, 6))
    V = np.zeros((npt, 3, 3))
    W = np.zeros((E, 6, 3))
    gc = np.zeros((nc, 6))
    gp = np.zeros((npt, 3))
    cost = 0.0
    A = np.zeros((3, 3))
    Jc = np.zeros((3, 6))
    Jp = np.zeros((3, 3))
    r = np.zeros(3)
    for e in range(E):
        k = obs_pose[e]
        j = obs_point[e]
        x = R[k, 0, 0] * X[j, 0] + R[k, 0, 1] * X[j, 1] + R[k, 0, 2] * X[j, 2] + t[k, 0]
        y = R[k, 1, 0] * X[j, 0] + R[k, 1, 1] * X[j, 1] + R[k, 1, 2] * X[j, 2] + t[k, 1]
        z = R[k, 2, 0] * X[j, 0] + R[k, 2, 1] * X[j, 1] + R[k, 2, 2] * X[j, 2] + t[k, 2]
        iz = 1.0 / z
        iz2 = iz * iz
        fx = intr[e, 0]
        fy = intr[e, 1]
        if fisheye:
            u, v = kb_project(x, y, z, cam[e])
            r[0] = u - uvr[e, 0]
            r[1] = v - uvr[e, 1]
        else:
            u = fx * x * iz + intr[e, 2]
            r[0] = u - uvr[e, 0]
            r[1] = fy * y * iz + intr[e, 3] - uvr[e, 1]
        rows = 2
        if stereo[e]:
            r[2] = u - bf[e] * iz - uvr[e, 2]
            rows = 3
        chi2 = 0.0
        for a in range(rows):
            chi2 += r[a] * r[a]
        chi2 *= info[e]
        d = delta[e]
        if robust and chi2 > d * d:
            cost += 2.0 * d * np.sqrt(chi2) - d * d
            w = info[e] * d / np.sqrt(chi2)
        else:
            cost += chi2
            w = info[e]
        if fisheye:
            kb_jacobian(x, y, z, cam[e], A)
        else:
            A[0, 0] = fx * iz
            A[0, 1] = 0.0
            A[0, 2] = -fx * x * iz2
            A[1, 0] = 0.0
            A[1, 1] = fy * iz
            A[1, 2] = -fy * y * iz2
            A[2, 0] = fx * iz
            A[2, 1] = 0.0
            A[2, 2] = (bf[e] - fx * x) * iz2
        ci = c[e]
        pi = p[e]
        for a in range(rows):
            Jc[a, 0] = y * A[a, 2] - z * A[a, 1]
            Jc[a, 1] = z * A[a, 0] - x * A[a, 2]
            Jc[a, 2] = x * A[a, 1] - y * A[a, 0]
            Jc[a, 3] = A[a, 0]
            Jc[a, 4] = A[a, 1]
            Jc[a, 5] = A[a, 2]
            for b in range(3):
                Jp[a, b] = A[a, 0] * R[k, 0, b] + A[a, 1] * R[k, 1, b] + A[a, 2] * R[k, 2, b]
        if ci >= 0:
            _accumulate_block(Jc, r, rows, w, gc[ci], U[ci])
        if pi >= 0:
            _accumulate_block(Jp, r, rows, w, gp[pi], V[pi])
        if ci >= 0 and pi >= 0:
            for i in range(6):
                for jj in range(3):
                    s = 0.0
                    for a in range(rows):
                        s += Jc[a, i] * Jp[a, jj]
                    W[e, i, jj] = w * s
    for q in range(nc):
        for i in range(6):
            for jj in range(i):
                U[q, i, jj] = U[q, jj, i]
    for q in range(npt):
        for i in range(3):
            for jj in range(i):
                V[q, i, jj] = V[q, jj, i]
    return U, V, W, gc, gp, cost


def _rotation(rng: np.random.Generator, scale: float) -> F64:
    """A rotation matrix of a random axis-angle of norm up to ``scale`` rad (Rodrigues)."""
    w = rng.normal(size=3) * scale
    th = float(np.linalg.norm(w))
    Kx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]) / th
    return np.eye(3) + np.sin(th) * Kx + (1.0 - np.cos(th)) * Kx @ Kx


def linearize_inputs(seed: int, fisheye: bool, robust: bool, K: int = 6, M: int = 80, E: int = 400) -> tuple:
    """Random ba_linearize arguments: K poses near the origin looking down +z at M points 2-6 m ahead, E observations
    (a third stereo unless ``fisheye``) with pixel noise of a few px (so some exceed the Huber threshold), two fixed
    poses (c = -1) and a few fixed points (p = -1)."""
    rng = np.random.default_rng(seed)
    R = np.stack([_rotation(rng, 0.1) for _ in range(K)])
    t = rng.normal(scale=0.2, size=(K, 3))
    X = np.column_stack([rng.uniform(-1.5, 1.5, M), rng.uniform(-1.0, 1.0, M), rng.uniform(2.0, 6.0, M)])
    obs_pose = rng.integers(0, K, E).astype(np.int64)
    obs_point = rng.integers(0, M, E).astype(np.int64)
    pose_map = np.array([-1, 0, 1, -1, 2, 3, *range(4, K - 2)], np.int64)[:K]
    nc = int(pose_map.max()) + 1
    point_fixed = rng.random(M) < 0.1
    point_map = np.full(M, -1, np.int64)
    point_map[~point_fixed] = np.arange(int((~point_fixed).sum()))
    npt = int((~point_fixed).sum())
    intr = np.tile([520.0, 515.0, 320.0, 240.0], (E, 1)) + rng.normal(scale=1.0, size=(E, 4))
    cam = np.column_stack([intr, np.tile([0.01, -0.005, 0.002, -0.001], (E, 1))]) if fisheye else np.zeros((E, 8))
    p_c = np.einsum("eij,ej->ei", R[obs_pose], X[obs_point]) + t[obs_pose]
    uvr = np.zeros((E, 3))
    uvr[:, 0] = intr[:, 0] * p_c[:, 0] / p_c[:, 2] + intr[:, 2] + rng.normal(scale=2.0, size=E)
    uvr[:, 1] = intr[:, 1] * p_c[:, 1] / p_c[:, 2] + intr[:, 3] + rng.normal(scale=2.0, size=E)
    bf = np.full(E, 40.0)
    stereo = np.zeros(E, bool) if fisheye else rng.random(E) < 0.35
    uvr[:, 2] = uvr[:, 0] - bf / p_c[:, 2] + rng.normal(scale=2.0, size=E)
    info = 1.2 ** (-2.0 * rng.integers(0, 8, E))
    delta = np.where(stereo, np.sqrt(7.815), np.sqrt(5.991))
    return (
        R, t, X, obs_pose, obs_point, pose_map[obs_pose], point_map[obs_point], uvr, stereo, intr, bf, info, delta,
        robust, nc, npt, cam, fisheye,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("seed", "fisheye", "robust"), [(0, False, True), (1, False, False), (2, True, True), (3, True, False)]
)
def test_linearize_is_the_former_loops_to_the_bit(seed: int, fisheye: bool, robust: bool) -> None:
    """U, V, W, gc, gp and the cost equal the former loops' in every bit (a changed summation order or a skipped
    product that was read would show in the last bits); W comes transposed in rows of 8 lanes (WT (E, 3, 8), lanes 6
    and 7 zero); W's rows of observations with a fixed end are zero."""
    args = linearize_inputs(seed, fisheye, robust)
    U, V, WT, gc, gp, cost = ba_linearize(*args)
    want = _former_linearize(*args)
    got: list[Any] = [U, V, WT, gc, gp, cost]
    assert WT.shape == (want[2].shape[0], 3, 8) and WT.flags.c_contiguous
    assert not WT[:, :, 6:].any()
    got[2] = WT[:, :, :6].transpose(0, 2, 1)
    for g, w in zip(got[:5], want[:5], strict=True):
        assert g.shape == w.shape
        np.testing.assert_array_equal(g.view(np.int64), w.view(np.int64))
    assert got[5] == want[5]
    c, p = args[5], args[6]
    assert (c < 0).any() and (p < 0).any() and (got[0] != 0.0).any() and got[2].any()
    assert not WT[(c < 0) | (p < 0)].any()
    if robust:
        plain = list(args)
        plain[13] = False
        assert _former_linearize(*plain)[5] > want[5]  # some observations are down-weighted: the robust branch runs
