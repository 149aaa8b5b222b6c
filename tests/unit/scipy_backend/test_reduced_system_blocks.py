"""slamkit_scipy.kernels.ba_reduced_system, which accumulates S's 6x6 blocks in 64-byte-aligned rows and copies them
into the dense matrix, against its former form accumulating in the dense matrix directly (slamkit 6c129bc), compiled
here with the same flags and the same SIMD intrinsics: S (every entry, the lower triangle included), rhs and V^-1 must
be equal to the bit, with and without a keyframe observing a point twice (a rig's scalar path), for several sizes
(one free pose; more than 64 observations of one point, which regrows the per-point scratch). Since branch lmcpu23
the kernel reads W as ba_linearize returns it, transposed in rows of 8 lanes (WT (E, 3, 8)); the former form here
takes the (E, 6, 3) blocks and transposes them per point, with its own instance of the W-rows intrinsic."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from slamkit_scipy.kernels import (
    _SCHUR_FASTMATH,
    _U6,
    _inv3,
    _make_block_update,
    _sub_block_diag,
    _sub_block_yw,
    _y_transposed,
    ba_reduced_system,
)

#: W_b Y_a^T into the block (cb, ca) with A = W_b read from the (E, 6, 3) blocks (a_row 3, a_col 1), as before lmcpu23
_sub_block_wy = _make_block_update(2, 3, 1, upper=False)


def as_wt(W: np.ndarray) -> np.ndarray:
    """(E, 6, 3) blocks -> ba_linearize's layout (E, 3, 8): transposed, lanes 6 and 7 zero."""
    WT = np.zeros((W.shape[0], 3, 8))
    WT[:, :, :6] = W.transpose(0, 2, 1)
    return WT


@numba.njit(nogil=True, fastmath=_SCHUR_FASTMATH)
def _former_reduced_system(U, V, W, gc, gp, lam, c, point_ptr, point_obs):  # type: ignore[no-untyped-def]
    """ba_reduced_system as it was at 6c129bc (S accumulated in the dense (6 nc, 6 nc) matrix), term for term."""
    nc = U.shape[0]
    npt = V.shape[0]
    n6 = 6 * nc
    S = np.zeros((n6, n6))
    rhs = np.zeros(n6)
    Vinv = np.zeros((npt, 3, 3))
    for q in range(nc):
        for i in range(6):
            rhs[6 * q + i] = -gc[q, i]
            for jj in range(6):
                S[6 * q + i, 6 * q + jj] = U[q, i, jj]
            S[6 * q + i, 6 * q + i] += lam
    Vd = np.zeros((3, 3))
    YT = np.zeros((64, 3, 8))
    WT = np.zeros((64, 3, 8))
    cs = np.zeros(64, np.uint64)
    es = np.zeros(64, np.int64)
    un6 = np.uint64(n6)
    for q in range(npt):
        for i in range(3):
            for jj in range(3):
                Vd[i, jj] = V[q, i, jj]
            Vd[i, i] += lam
        _inv3(Vd, Vinv[q])
        start = point_ptr[q]
        n = point_ptr[q + 1] - start
        if n == 0:
            continue
        if YT.shape[0] < n:
            YT = np.zeros((n, 3, 8))
            WT = np.zeros((n, 3, 8))
            cs = np.zeros(n, np.uint64)
            es = np.zeros(n, np.int64)
        for a in range(n):
            e = point_obs[start + a]
            es[a] = e
            cs[a] = np.uint64(c[e])
            for i in range(6):
                for k in range(3):
                    WT[a, k, i] = W[e, i, k]
            _y_transposed(YT, 24 * a, WT, 24 * a, Vinv, 9 * q)
            ca = c[e]
            for i in range(6):
                rhs[6 * ca + i] += YT[a, 0, i] * gp[q, 0] + YT[a, 1, i] * gp[q, 1] + YT[a, 2, i] * gp[q, 2]
        for a in range(n):
            ca = cs[a]
            for b in range(a, n):
                cb = cs[b]
                if ca < cb:
                    _sub_block_yw(S, _U6 * ca * un6 + _U6 * cb, n6, YT, 24 * a, WT, 24 * b)
                elif ca > cb:
                    _sub_block_wy(S, _U6 * cb * un6 + _U6 * ca, n6, W, 18 * es[b], YT, 24 * a)
                elif a == b:
                    _sub_block_diag(S, _U6 * ca * un6 + _U6 * ca, n6, YT, 24 * a, WT, 24 * b)
                else:
                    eb = es[b]
                    for i in range(6):
                        for jj in range(6):
                            v = YT[a, 0, i] * W[eb, jj, 0] + YT[a, 1, i] * W[eb, jj, 1] + YT[a, 2, i] * W[eb, jj, 2]
                            S[_U6 * ca + np.uint64(i), _U6 * ca + np.uint64(jj)] -= v
                            S[_U6 * ca + np.uint64(jj), _U6 * ca + np.uint64(i)] -= v
    return S, rhs, Vinv


def _problem(seed: int, nc: int, npt: int, twice: bool, max_obs: int) -> tuple:
    """A reduced-system input: each point observed by 1..max_obs free poses (with repeats when max_obs > nc), in a
    random order, its observations scattered over W's rows; ``twice``: ~30% of the points seen twice by one pose."""
    rng = np.random.default_rng(seed)
    c_list: list[int] = []
    obs: list[int] = []
    ptr = [0]
    for _ in range(npt):
        n = int(rng.integers(1, max_obs + 1))
        poses = [int(k) for k in (rng.permutation(nc)[:n] if n <= nc else rng.integers(0, nc, n))]
        if twice and rng.random() < 0.3:
            poses.insert(int(rng.integers(0, len(poses) + 1)), poses[0])
        for k in poses:
            obs.append(len(c_list))
            c_list.append(k)
        ptr.append(len(obs))
    E = len(c_list)
    order = rng.permutation(E)
    A = rng.normal(size=(nc, 6, 6))
    B = rng.normal(size=(npt, 3, 3))
    return (
        np.einsum("kij,klj->kil", A, A) + 6 * np.eye(6),
        np.einsum("kij,klj->kil", B, B) + 3 * np.eye(3),
        rng.normal(size=(E, 6, 3)) * np.exp(rng.normal(size=(E, 1, 1))),
        rng.normal(size=(nc, 6)),
        rng.normal(size=(npt, 3)),
        float(rng.uniform(1e-4, 10.0)),
        np.array(c_list, np.int64)[order],
        np.array(ptr, np.int64),
        np.argsort(order)[np.array(obs, np.int64)].astype(np.int64),
    )


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.int64)


@pytest.mark.parametrize(
    ("seed", "nc", "npt", "twice", "max_obs"),
    [(0, 1, 20, False, 1), (1, 7, 80, False, 7), (2, 25, 300, False, 12), (3, 9, 60, True, 9), (4, 5, 6, False, 90)],
)
def test_blocked_reduced_system_is_the_former_to_the_bit(
    seed: int, nc: int, npt: int, twice: bool, max_obs: int
) -> None:
    args = _problem(seed, nc, npt, twice, max_obs)
    wt_args = list(args)
    wt_args[2] = as_wt(args[2])
    got = ba_reduced_system(*wt_args)
    want = _former_reduced_system(*args)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape
        assert np.array_equal(_bits(g), _bits(w))
