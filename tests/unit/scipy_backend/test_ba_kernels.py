"""The bundle adjustment's reduced camera system and Cholesky kernels (slamkit_scipy.kernels) against straightforward
per-entry Python references (the Cholesky: the same floating-point operations in the same order, so equal to the bit;
the reduced system, compiled with fast-math contraction: to rounding), and against dense linear algebra."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from slamkit_scipy.kernels import ba_reduced_system, ba_retract, cholesky_solve_upper
from slamkit_scipy.lie import se3_exp_batch

from slamkit.geometry.se3_kernels import se3_exp_times

F64 = np.ndarray


def _inv3_reference(M: F64) -> F64:
    """The kernels' closed-form 3x3 inverse (cofactors over the determinant), in Python floats."""
    a, b, c = (float(v) for v in M[0])
    d, e, f = (float(v) for v in M[1])
    g, h, i = (float(v) for v in M[2])
    A = e * i - f * h
    Bc = -(d * i - f * g)
    C = d * h - e * g
    inv = 1.0 / (a * A + b * Bc + c * C)
    return np.array(
        [
            [A * inv, -(b * i - c * h) * inv, (b * f - c * e) * inv],
            [Bc * inv, (a * i - c * g) * inv, -(a * f - c * d) * inv],
            [C * inv, -(a * h - b * g) * inv, (a * e - b * d) * inv],
        ]
    )


def reduced_system_reference(
    U: F64, V: F64, W: F64, gc: F64, gp: F64, lam: float, c: F64, ptr: F64, obs: F64
) -> tuple[F64, F64, F64]:
    """S = U + lam I - sum_q W_q (V_q + lam I)^-1 W_q^T one entry at a time: for each point in order, each pair
    (a <= b) of its observations adds Y_a W_b^T (Y_a = W_a (V_q + lam I)^-1) to block (c_a, c_b), or its transpose to
    block (c_b, c_a) when c_a > c_b; a keyframe observing the point twice gets both halves of the diagonal block."""
    nc, npt = U.shape[0], V.shape[0]
    S = np.zeros((6 * nc, 6 * nc))
    rhs = np.zeros(6 * nc)
    Vinv = np.zeros((npt, 3, 3))
    for k in range(nc):
        S[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = U[k] + lam * np.eye(6)
        rhs[6 * k : 6 * k + 6] = -gc[k]
    for q in range(npt):
        Vinv[q] = _inv3_reference(V[q] + lam * np.eye(3))
        rows = [int(e) for e in obs[ptr[q] : ptr[q + 1]]]
        Y = [[[W[e, i, 0] * Vinv[q, 0, k] + W[e, i, 1] * Vinv[q, 1, k] + W[e, i, 2] * Vinv[q, 2, k] for k in range(3)]
              for i in range(6)] for e in rows]  # fmt: skip
        for a, e in enumerate(rows):
            for i in range(6):
                rhs[6 * c[e] + i] += Y[a][i][0] * gp[q, 0] + Y[a][i][1] * gp[q, 1] + Y[a][i][2] * gp[q, 2]
        for a, ea in enumerate(rows):
            for b in range(a, len(rows)):
                eb = rows[b]
                ca, cb = int(c[ea]), int(c[eb])
                for i in range(6):
                    for j in range(6):
                        v = Y[a][i][0] * W[eb, j, 0] + Y[a][i][1] * W[eb, j, 1] + Y[a][i][2] * W[eb, j, 2]
                        if ca < cb:
                            S[6 * ca + i, 6 * cb + j] -= v
                        elif ca > cb:
                            S[6 * cb + j, 6 * ca + i] -= v
                        else:
                            S[6 * ca + i, 6 * ca + j] -= v
                            if b != a:
                                S[6 * ca + j, 6 * ca + i] -= v
    return S, rhs, Vinv


def as_wt(W: F64) -> F64:
    """(E, 6, 3) blocks -> the kernels' layout (ba_linearize's WT (E, 3, 8)): transposed, lanes 6 and 7 zero."""
    WT = np.zeros((W.shape[0], 3, 8))
    WT[:, :, :6] = W.transpose(0, 2, 1)
    return WT


def random_problem(seed: int, nc: int, npt: int, twice: bool) -> tuple:
    """A random reduced-system input: each point observed by 1..nc free poses in a random order (as a local BA's
    keyframe-id order against its free-pose order), ``twice``: some poses observe a point a second time (a rig)."""
    rng = np.random.default_rng(seed)
    c_list: list[int] = []
    obs: list[int] = []
    ptr = [0]
    for _ in range(npt):
        poses = list(rng.permutation(nc)[: rng.integers(1, nc + 1)])
        if twice and rng.random() < 0.3:
            poses.insert(int(rng.integers(0, len(poses) + 1)), poses[0])
        for k in poses:
            obs.append(len(c_list))
            c_list.append(int(k))
        ptr.append(len(obs))
    E = len(c_list)
    order = rng.permutation(E)  # the observations of a point are not adjacent rows of W
    c = np.array(c_list, np.int64)[order]
    obs_rows = np.argsort(order)[np.array(obs, np.int64)]
    A = rng.normal(size=(nc, 6, 6))
    B = rng.normal(size=(npt, 3, 3))
    return (
        np.einsum("kij,klj->kil", A, A) + 6 * np.eye(6),
        np.einsum("kij,klj->kil", B, B) + 3 * np.eye(3),
        rng.normal(size=(E, 6, 3)),
        rng.normal(size=(nc, 6)),
        rng.normal(size=(npt, 3)),
        0.37,
        c,
        np.array(ptr, np.int64),
        obs_rows.astype(np.int64),
    )


@pytest.mark.parametrize(("seed", "twice"), [(0, False), (1, False), (2, True), (3, True)])
def test_reduced_system_is_the_reference(seed: int, twice: bool) -> None:
    """S's upper triangle (all the Cholesky kernel reads) and rhs equal the reference to rounding (the kernel's
    fast-math flags let the compiler fuse and reorder each entry's three products: 1e-12 relative to the entry's
    scale, where a wrong pair or a missed transposition would be off by O(1)), V^-1 likewise; the blocks strictly
    below the diagonal blocks are left 0."""
    args = random_problem(seed, nc=7, npt=60, twice=twice)
    wt_args = list(args)
    wt_args[2] = as_wt(args[2])
    got, want = ba_reduced_system(*wt_args), reduced_system_reference(*args)
    upper = np.triu(np.ones(want[0].shape, bool))
    assert got[0].shape == want[0].shape
    scale = np.abs(want[0][upper]).max()
    np.testing.assert_allclose(got[0][upper], want[0][upper], rtol=0.0, atol=1e-12 * scale)
    block_lower = np.tril(np.ones(want[0].shape, bool), -1) & ~np.kron(np.eye(7, dtype=bool), np.ones((6, 6), bool))
    assert not got[0][block_lower].any()
    assert got[1].shape == want[1].shape
    np.testing.assert_allclose(got[1], want[1], rtol=0.0, atol=1e-12 * np.abs(want[1]).max())
    np.testing.assert_allclose(got[2], want[2], rtol=0.0, atol=1e-12 * np.abs(want[2]).max())


def _fma(a: float, b: float, c: float) -> float:
    """a b + c rounded once (the exact value as a Fraction, then float(): CPython rounds an int ratio correctly)."""
    return float(Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c)))


@pytest.mark.parametrize("seed", [5, 6])
def test_reduced_system_pair_blocks_to_the_bit(seed: int) -> None:
    """The SIMD pair updates of ba_reduced_system perform, per entry, exactly the documented fused operations: Y_a[i, k]
    = fma(W_a[i, 2], Vi[2, k], fma(W_a[i, 1], Vi[1, k], W_a[i, 0] Vi[0, k])); an off-diagonal block entry t = Y_a[i, 2]
    W_b[j, 2], t = fma(Y_a[i, 1], W_b[j, 1], t), t = fma(Y_a[i, 0], W_b[j, 0], t), S -= t (the same t transposed when
    c_a > c_b); a diagonal block's upper entry t = Y_a[i, 0] W_a[j, 0], then fma with k = 1, 2. So S's upper triangle
    equals this exact-FMA reference to the bit; the masked lanes write nothing: a diagonal block's lower triangle is
    U + lam I, every block below the diagonal blocks 0. (One rounding more or less, or another order, would differ.)"""
    U, V, W, gc, gp, lam, c, ptr, obs = random_problem(seed, nc=5, npt=30, twice=False)
    nc, npt = U.shape[0], V.shape[0]
    S, _, Vinv = ba_reduced_system(U, V, as_wt(W), gc, gp, lam, c, ptr, obs)
    want = np.zeros((6 * nc, 6 * nc))
    for k in range(nc):
        want[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = U[k]
        want[np.arange(6 * k, 6 * k + 6), np.arange(6 * k, 6 * k + 6)] += lam
    for q in range(npt):
        Vi = Vinv[q]
        np.testing.assert_allclose(Vi, _inv3_reference(V[q] + lam * np.eye(3)), rtol=1e-13)
        rows = [int(e) for e in obs[ptr[q] : ptr[q + 1]]]
        Y = np.array([[[_fma(W[e, i, 2], Vi[2, k], _fma(W[e, i, 1], Vi[1, k], W[e, i, 0] * Vi[0, k])) for k in range(3)]
                       for i in range(6)] for e in rows])  # fmt: skip
        for a, ea in enumerate(rows):
            for b in range(a, len(rows)):
                eb = rows[b]
                ca, cb = int(c[ea]), int(c[eb])
                for i in range(6):
                    for j in range(6):
                        y, w = Y[a, i], W[eb, j]
                        if ca != cb:
                            t = _fma(y[0], w[0], _fma(y[1], w[1], y[2] * w[2]))
                            r, s = (6 * ca + i, 6 * cb + j) if ca < cb else (6 * cb + j, 6 * ca + i)
                            want[r, s] -= t
                        elif j >= i:
                            want[6 * ca + i, 6 * ca + j] -= _fma(y[2], w[2], _fma(y[1], w[1], y[0] * w[0]))
    upper = np.triu(np.ones(want.shape, bool))
    assert np.array_equal(S[upper].view(np.int64), want[upper].view(np.int64))
    assert np.array_equal(S[~upper], want[~upper])  # diagonal blocks' lower triangles U + lam I, 0 elsewhere


def test_reduced_system_is_the_schur_complement() -> None:
    U, V, W, gc, gp, lam, c, ptr, obs = random_problem(4, nc=5, npt=40, twice=False)
    nc, npt = U.shape[0], V.shape[0]
    Wd = np.zeros((6 * nc, 3 * npt))
    for q in range(npt):
        for e in obs[ptr[q] : ptr[q + 1]]:
            Wd[6 * c[e] : 6 * c[e] + 6, 3 * q : 3 * q + 3] += W[e]
    Vi = np.zeros((3 * npt, 3 * npt))
    for q in range(npt):
        Vi[3 * q : 3 * q + 3, 3 * q : 3 * q + 3] = np.linalg.inv(V[q] + lam * np.eye(3))
    Ud = np.zeros((6 * nc, 6 * nc))
    for k in range(nc):
        Ud[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = U[k]
    S_want = Ud + lam * np.eye(6 * nc) - Wd @ Vi @ Wd.T
    S, rhs, _ = ba_reduced_system(U, V, as_wt(W), gc, gp, lam, c, ptr, obs)
    upper = np.triu(np.ones((6 * nc, 6 * nc), bool))
    np.testing.assert_allclose(S[upper], S_want[upper], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(rhs, -gc.ravel() + Wd @ Vi @ gp.ravel(), rtol=1e-10, atol=1e-10)


def cholesky_reference(S: F64, rhs: F64) -> F64:
    """Right-looking Cholesky S = R^T R of the upper triangle, one entry at a time, then the two triangular solves."""
    n = S.shape[0]
    R = S.copy()
    x = rhs.copy()
    for j in range(n):
        if not R[j, j] > 0.0:
            return np.full(n, np.nan)
        d = float(np.sqrt(R[j, j]))
        R[j, j] = d
        inv = 1.0 / d
        for k in range(j + 1, n):
            R[j, k] *= inv
        for i in range(j + 1, n):
            f = R[j, i]
            if f != 0.0:
                for k in range(i, n):
                    R[i, k] -= f * R[j, k]
    for j in range(n):
        x[j] /= R[j, j]
        for k in range(j + 1, n):
            x[k] -= R[j, k] * x[j]
    for j in range(n - 1, -1, -1):
        s = x[j]
        for k in range(j + 1, n):
            s -= R[j, k] * x[k]
        x[j] = s / R[j, j]
    return x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cholesky_is_the_reference_to_the_bit(seed: int) -> None:
    """On symmetric positive-definite systems of 6x6 blocks, some of them zero (skipped multipliers), with garbage in
    the strictly lower triangle (never read)."""
    rng = np.random.default_rng(seed)
    n = 6 * 9
    A = rng.uniform(-1.0, 1.0, size=(n, n))
    S = A + A.T
    zero = np.kron(rng.random((9, 9)) < 0.4, np.ones((6, 6), bool))
    S[zero | zero.T] = 0.0
    S += 2.0 * n * np.eye(n)  # diagonally dominant: positive definite
    S[np.tril_indices(n, -1)] = 1e300
    rhs = rng.normal(size=n)
    got = cholesky_solve_upper(S, rhs)
    assert np.all(np.isfinite(got))
    assert np.array_equal(got.view(np.int64), cholesky_reference(S, rhs).view(np.int64))
    np.testing.assert_allclose(got, np.linalg.solve(np.triu(S) + np.triu(S, 1).T, rhs), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-9, 1e-5, 1e-3, 0.1, 1.0, 3.0])
def test_retract_is_the_batched_exponential(scale: float) -> None:
    """ba_retract: the free poses become exp(xi) T (slamkit_scipy.lie.se3_exp_batch, both sides of the small-angle
    series switch) to rounding, and bit for bit the shared compiled kernel slamkit.geometry.se3_kernels.se3_exp_times
    (tracking's pose optimization retracts with it too); the free points X + dp exactly; the fixed poses and points
    are untouched and the inputs are not written."""
    rng = np.random.default_rng(int(scale * 1e9) % 2**32)
    K, M = 9, 20
    T = se3_exp_batch(rng.normal(size=(K, 6)))
    X = rng.normal(size=(M, 3))
    T0, X0 = T.copy(), X.copy()
    free_poses = np.array([1, 3, 4, 8], np.int64)
    free_points = np.array([0, 5, 7], np.int64)
    h = rng.normal(size=6 * free_poses.size + 3 * free_points.size) * scale
    Tn, Xn = ba_retract(T, X, free_poses, free_points, h)
    want = T.copy()
    want[free_poses] = se3_exp_batch(h[:24].reshape(4, 6)) @ T[free_poses]
    np.testing.assert_allclose(Tn, want, rtol=0.0, atol=4e-15)
    for q, k in enumerate(free_poses):
        assert np.array_equal(Tn[k], se3_exp_times(h[6 * q : 6 * q + 6], T[k]))
    fixed = np.setdiff1d(np.arange(K), free_poses)
    assert np.array_equal(Tn[fixed], T[fixed])
    wantX = X.copy()
    wantX[free_points] += h[24:].reshape(3, 3)
    assert np.array_equal(Xn, wantX)
    assert np.array_equal(T, T0) and np.array_equal(X, X0)
