"""numba kernels of the bundle-adjustment hot path (nogil: a BA in a thread leaves the GIL to the others).

One pass over the observations builds the Gauss-Newton blocks (the same Jacobians as slamkit_scipy.reprojection,
which the tests check against finite differences), and one pass over the points forms the reduced camera
system of the Schur complement, so no (E, 6, 6)-sized temporaries are allocated per iteration.
Layout: poses enter as all K rotations/translations; c (E,) / p (E,) map each observation to its free pose /
free point index or -1; residual rows are (u, v, u_right) with the third row unused for monocular observations.
Fisheye problems (``fisheye``) project with the Kannala-Brandt model (slamkit.optim.kannala_brandt), cam (E, 8) =
fx, fy, cx, cy, k1..k4 per observation; the pinhole path reads intr (E, 4) as before.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from llvmlite import ir
from llvmlite.binding import llvm_version_info
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import NDArray

from slamkit.geometry.se3_kernels import se3_exp_times
from slamkit.optim.kannala_brandt import kb_jacobian, kb_project

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@numba.njit(cache=True, nogil=True, inline="always")
def _accumulate_block(J: F64, r: F64, rows: int, w: float, g: F64, H: F64) -> None:  # pragma: no cover - compiled
    """g += w J^T r and the upper triangle of H += w J^T J, over the first ``rows`` residual rows.

    J: (3, n) Jacobian of one observation with respect to one block (n = 6 for a pose, 3 for a point); g: (n,),
    H: (n, n) views into the block's gradient and Hessian."""
    n = g.shape[0]
    for i in range(n):
        gi = 0.0
        for a in range(rows):
            gi += J[a, i] * r[a]
        g[i] += w * gi
        for jj in range(i, n):
            s = 0.0
            for a in range(rows):
                s += J[a, i] * J[a, jj]
            H[i, jj] += w * s


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def ba_linearize(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    c: I64,
    p: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
    delta: F64,
    robust: bool,
    nc: int,
    npt: int,
    cam: F64,
    fisheye: bool,
) -> tuple[F64, F64, F64, F64, F64, float]:  # pragma: no cover - compiled
    """-> U (nc, 6, 6), V (npt, 3, 3), WT (E, 3, 8), gc (nc, 6), gp (npt, 3), robust cost. WT holds each
    observation's W = J_pose^T w J_point (6 x 3) transposed in rows of 8 lanes, WT[e, k, i] = W_e[i, k] for i < 6 and
    0 in lanes 6 and 7 (all 0 unless both ends are free): the layout the reduced camera system's 8-lane updates read,
    written here once per linearization instead of transposed there once per LM trial (branch lmcpu23). Blocks are
    J^T w J and J^T w r with w = info * rho'(chi2) (IRLS Huber when ``robust``).
    Compiled with contraction (fastmath "contract": a multiply and the add it feeds may become one fused multiply-add,
    one rounding instead of two; 0.93x the kernel's time on captured fr1 local BAs, U within ~5e-12 relative).
    The pose Jacobian of an observation by a fixed pose is not formed (nothing reads it), WT is allocated empty and
    only its lanes 6 and 7, and the rows of observations with a fixed end, are zeroed, and the blocks' sums over the residual rows are
    written out (rows 0 and 1, row 2 when stereo; fixed block sizes, no loop over a run-time row count innermost):
    the same products summed in the same order from 0.0, so every value returned is unchanged to the bit
    (tests/unit/scipy_backend/test_ba_linearize_bits.py compares them with the former loops); 0.88x the kernel's
    time on captured fr1 local BAs."""
    E = obs_pose.shape[0]
    U = np.zeros((nc, 6, 6))
    V = np.zeros((npt, 3, 3))
    WT = np.empty((E, 3, 8))
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
            kb_jacobian(x, y, z, cam[e], A)  # rows 0 and 1; a fisheye observation has no third row
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
        three = rows == 3
        for a in range(rows):
            # d r / d omega = cross(p_c, A[a]); d r / d v = A[a]; d r / d X = A[a] R
            if ci >= 0:
                Jc[a, 0] = y * A[a, 2] - z * A[a, 1]
                Jc[a, 1] = z * A[a, 0] - x * A[a, 2]
                Jc[a, 2] = x * A[a, 1] - y * A[a, 0]
                Jc[a, 3] = A[a, 0]
                Jc[a, 4] = A[a, 1]
                Jc[a, 5] = A[a, 2]
            for b in range(3):
                Jp[a, b] = A[a, 0] * R[k, 0, b] + A[a, 1] * R[k, 1, b] + A[a, 2] * R[k, 2, b]
        # g += w J^T r and the upper triangle of H += w J^T J (_accumulate_block's sums with the rows written out)
        if ci >= 0:
            for i in range(6):
                gi = 0.0
                gi += Jc[0, i] * r[0]
                gi += Jc[1, i] * r[1]
                if three:
                    gi += Jc[2, i] * r[2]
                gc[ci, i] += w * gi
                for jj in range(i, 6):
                    s = 0.0
                    s += Jc[0, i] * Jc[0, jj]
                    s += Jc[1, i] * Jc[1, jj]
                    if three:
                        s += Jc[2, i] * Jc[2, jj]
                    U[ci, i, jj] += w * s
        if pi >= 0:
            for i in range(3):
                gi = 0.0
                gi += Jp[0, i] * r[0]
                gi += Jp[1, i] * r[1]
                if three:
                    gi += Jp[2, i] * r[2]
                gp[pi, i] += w * gi
                for jj in range(i, 3):
                    s = 0.0
                    s += Jp[0, i] * Jp[0, jj]
                    s += Jp[1, i] * Jp[1, jj]
                    if three:
                        s += Jp[2, i] * Jp[2, jj]
                    V[pi, i, jj] += w * s
        if ci >= 0 and pi >= 0:
            for i in range(6):
                for jj in range(3):
                    s = 0.0
                    s += Jc[0, i] * Jp[0, jj]
                    s += Jc[1, i] * Jp[1, jj]
                    if three:
                        s += Jc[2, i] * Jp[2, jj]
                    WT[e, jj, i] = w * s
            for jj in range(3):
                WT[e, jj, 6] = 0.0
                WT[e, jj, 7] = 0.0
        else:
            for jj in range(3):
                for i in range(8):
                    WT[e, jj, i] = 0.0
    # Mirror the upper triangles.
    for q in range(nc):
        for i in range(6):
            for jj in range(i):
                U[q, i, jj] = U[q, jj, i]
    for q in range(npt):
        for i in range(3):
            for jj in range(i):
                V[q, i, jj] = V[q, jj, i]
    return U, V, WT, gc, gp, cost


@numba.njit(cache=True, nogil=True)
def _inv3(M: F64, out: F64) -> None:  # pragma: no cover - compiled
    """Closed-form inverse of a 3x3 matrix into ``out`` (inf/NaN when singular: the step is then rejected)."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 0], M[1, 1], M[1, 2]
    g, h, i = M[2, 0], M[2, 1], M[2, 2]
    A = e * i - f * h
    Bc = -(d * i - f * g)
    C = d * h - e * g
    det = a * A + b * Bc + c * C
    inv = 1.0 / det
    out[0, 0] = A * inv
    out[1, 0] = Bc * inv
    out[2, 0] = C * inv
    out[0, 1] = -(b * i - c * h) * inv
    out[1, 1] = (a * i - c * g) * inv
    out[2, 1] = -(a * h - b * g) * inv
    out[0, 2] = (b * f - c * e) * inv
    out[1, 2] = -(a * f - c * d) * inv
    out[2, 2] = (a * e - b * d) * inv


#: Unsigned block offsets for the compiled kernels' indices: numba tests a signed index for wraparound (a negative index
#: counts from the end) at every access, an unsigned one it does not (uint64 + int64 would be float64 in numba).
_U6 = np.uint64(6)


# ---- explicit SIMD rows of the reduced camera system (branch lbacpu) ---------------------------------------------
#
# numba leaves LLVM's SLP vectorizer off and fully unrolls 6-trip loops before the loop vectorizer sees them, so a
# 6x6 block update written in Python stays scalar however it is written (docs/BENCHMARKS.md, branches lmfr1 and
# lmsolve). The intrinsics below emit the vector IR directly: one row of a 6x6 block of S is one 8-lane vector
# (lanes 6 and 7 masked off: llvm.masked.load / llvm.masked.store, one AVX-512 instruction each where the CPU has it,
# a pair of AVX2 masked moves or scalar code elsewhere), updated with one multiply and two fused multiply-adds
# (llvm.fma, exact IEEE fused operations: no fast-math flag lets LLVM reorder them). Each entry therefore receives
# exactly the operations the previous scalar kernel (rows of 6 scalar updates compiled with _SCHUR_FASTMATH) performed
# on this project's machines (x86-64 with FMA; read from its assembly): an off-diagonal entry t = a2 b2, t = fma(a1, b1, t), t = fma(a0, b0, t),
# S -= t; a diagonal block's entry the same from k = 0 up; Y = W V^-1 from k = 0 up. S, rhs and V^-1 equal the
# scalar kernel's bit for bit on 182 captured fr1_xyz local BAs (/work/ref/s20/lbacpu/tools/schur_ab.py), and the
# trajectories of whole runs are unchanged (docs/BENCHMARKS.md, section lbacpu).
# numba compiles these into ba_reduced_system's cache entry: after changing them, clear this module's numba cache.

_F64_IR = ir.DoubleType()
_I32_IR = ir.IntType(32)
_I64_IR = ir.IntType(64)
_V8_IR = ir.VectorType(_F64_IR, 8)
_M8_IR = ir.VectorType(ir.IntType(1), 8)


def _ir_function(module: ir.Module, name: str, ret: ir.Type, args: list[ir.Type]) -> ir.Function:
    return cgutils.get_or_insert_function(module, ir.FunctionType(ret, args), name)


def _ir_splat(builder: ir.IRBuilder, x: ir.Value) -> ir.Value:
    """An 8-lane vector of the scalar x."""
    v = builder.insert_element(ir.Constant(_V8_IR, ir.Undefined), x, ir.Constant(_I32_IR, 0))
    return builder.shuffle_vector(v, ir.Constant(_V8_IR, ir.Undefined), ir.Constant(ir.VectorType(_I32_IR, 8), [0] * 8))


def _ir_lane_load(builder: ir.IRBuilder, base: ir.Value, offset: int) -> ir.Value:
    """8 consecutive float64 from base + offset (the padded rows of the per-point scratch arrays)."""
    ptr = builder.gep(base, [ir.Constant(_I64_IR, offset)])
    return builder.load(builder.bitcast(ptr, _V8_IR.as_pointer()), align=8)


def _ir_masked_ops(builder: ir.IRBuilder, ptr_t: ir.Type) -> tuple[ir.Function, ir.Function, Any]:
    """llvm.masked.load / llvm.masked.store of 8 float64 lanes, and the cast of a ``double*`` row pointer to their
    pointer argument: LLVM 15+ (opaque pointers) names them by ``p0`` and takes the pointer as it is, LLVM 14 (numba
    0.60's llvmlite) by ``p0v8f64`` and takes an ``<8 x double>*``."""
    if llvm_version_info >= (15,):
        suffix, vptr_t = "p0", ptr_t
    else:
        suffix, vptr_t = "p0v8f64", _V8_IR.as_pointer()
    mod = builder.module
    mload = _ir_function(mod, f"llvm.masked.load.v8f64.{suffix}", _V8_IR, [vptr_t, _I32_IR, _M8_IR, _V8_IR])
    mstore = _ir_function(mod, f"llvm.masked.store.v8f64.{suffix}", ir.VoidType(), [_V8_IR, vptr_t, _I32_IR, _M8_IR])

    def as_row(ptr: ir.Value) -> ir.Value:
        return ptr if vptr_t is ptr_t else builder.bitcast(ptr, vptr_t)

    return mload, mstore, as_row


def _ir_int(context: Any, builder: ir.IRBuilder, value: ir.Value, ty: types.Type) -> ir.Value:
    return context.cast(builder, value, ty, types.int64)


def _make_block_update(k_first: int, a_row: int, a_col: int, upper: bool) -> Any:
    """An intrinsic ``f(S, s_off, s_stride, A, a_off, B, b_off)`` (C-contiguous float64 arrays, offsets in elements of
    their flat data): for i, j in 0..5 (j >= i only when ``upper``),
    S_flat[s_off + i s_stride + j] -= sum over k of A_flat[a_off + a_row i + a_col k] B_flat[b_off + 8 k + j],
    the three products summed from k = ``k_first`` (0 or 2) in one multiply and two fused multiply-adds, the sum then
    subtracted from S (module comment above). B holds three 8-lane rows (lanes 6 and 7 are read, never used)."""
    order = (0, 1, 2) if k_first == 0 else (2, 1, 0)

    @intrinsic
    def block_update(typingctx: Any, S: Any, s_off: Any, s_stride: Any, A: Any, a_off: Any, B: Any, b_off: Any) -> Any:
        sig = types.void(S, s_off, s_stride, A, a_off, B, b_off)

        def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: Any) -> Any:
            S_, so, ss, A_, ao, B_, bo = args
            at = signature.args
            s_data = context.make_array(at[0])(context, builder, S_).data
            a_data = context.make_array(at[3])(context, builder, A_).data
            b_data = context.make_array(at[5])(context, builder, B_).data
            so, ss = _ir_int(context, builder, so, at[1]), _ir_int(context, builder, ss, at[2])
            ao, bo = _ir_int(context, builder, ao, at[4]), _ir_int(context, builder, bo, at[6])
            mod = builder.module
            mload, mstore, as_row = _ir_masked_ops(builder, s_data.type)
            fma = _ir_function(mod, "llvm.fma.v8f64", _V8_IR, [_V8_IR, _V8_IR, _V8_IR])
            b_base = builder.gep(b_data, [bo])
            Bv = [_ir_lane_load(builder, b_base, 8 * k) for k in range(3)]
            a_base = builder.gep(a_data, [ao])
            zero = ir.Constant(_V8_IR, [0.0] * 8)
            align = ir.Constant(_I32_IR, 8)
            for i in range(6):
                mask = ir.Constant(_M8_IR, [int((i <= j or not upper) and j < 6) for j in range(8)])
                a = [builder.load(builder.gep(a_base, [ir.Constant(_I64_IR, a_row * i + a_col * k)])) for k in range(3)]
                row = as_row(builder.gep(s_data, [builder.add(so, builder.mul(ss, ir.Constant(_I64_IR, i)))]))
                s = builder.call(mload, [row, align, mask, zero])
                k0, k1, k2 = order
                t = builder.fmul(_ir_splat(builder, a[k0]), Bv[k0])
                t = builder.call(fma, [_ir_splat(builder, a[k1]), Bv[k1], t])
                t = builder.call(fma, [_ir_splat(builder, a[k2]), Bv[k2], t])
                builder.call(mstore, [builder.fsub(s, t), row, align, mask])
            return context.get_dummy_value()

        return sig, codegen

    return block_update


#: Y_a W_b^T into the block (ca, cb), ca < cb: A = Y_a^T (scratch YT, a_row 1, a_col 8), B = W_b^T (WT's rows).
_sub_block_yw = _make_block_update(2, 1, 8, upper=False)
#: W_b Y_a^T into the block (cb, ca), cb < ca: A = W_b (read from WT (E, 3, 8): a_row 1, a_col 8), B = Y_a^T (YT).
_sub_block_wy = _make_block_update(2, 1, 8, upper=False)
#: A point's own diagonal block Y_a W_a^T, its upper triangle only (the Cholesky kernel reads no other entry).
_sub_block_diag = _make_block_update(0, 1, 8, upper=True)


def _y_transposed_typer(typingctx: Any, YT: Any, y_off: Any, WT: Any, w_off: Any, Vinv: Any, v_off: Any) -> Any:
    """YT_flat[y_off + 8 k + i] = Y[i, k] = fma(W[i, 2], Vi[2, k], fma(W[i, 1], Vi[1, k], W[i, 0] Vi[0, k])) for all 8
    lanes i (W^T's padded rows WT_flat[w_off + 8 m + i]; Vi = Vinv_flat[v_off:v_off + 9], row-major 3x3): one
    observation's Y = W (V + lam I)^-1, transposed, in three 8-lane vectors."""
    sig = types.void(YT, y_off, WT, w_off, Vinv, v_off)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: Any) -> Any:
        Y_, yo, W_, wo, V_, vo = args
        at = signature.args
        y_data = context.make_array(at[0])(context, builder, Y_).data
        w_data = context.make_array(at[2])(context, builder, W_).data
        v_data = context.make_array(at[4])(context, builder, V_).data
        yo, wo, vo = (_ir_int(context, builder, x, t) for x, t in ((yo, at[1]), (wo, at[3]), (vo, at[5])))
        fma = _ir_function(builder.module, "llvm.fma.v8f64", _V8_IR, [_V8_IR, _V8_IR, _V8_IR])
        w_base = builder.gep(w_data, [wo])
        Wv = [_ir_lane_load(builder, w_base, 8 * m) for m in range(3)]
        v_base = builder.gep(v_data, [vo])
        y_base = builder.gep(y_data, [yo])
        for k in range(3):
            v = [builder.load(builder.gep(v_base, [ir.Constant(_I64_IR, 3 * m + k)])) for m in range(3)]
            t = builder.fmul(Wv[0], _ir_splat(builder, v[0]))
            t = builder.call(fma, [Wv[1], _ir_splat(builder, v[1]), t])
            t = builder.call(fma, [Wv[2], _ir_splat(builder, v[2]), t])
            out = builder.gep(y_base, [ir.Constant(_I64_IR, 8 * k)])
            builder.store(t, builder.bitcast(out, _V8_IR.as_pointer()), align=8)
        return context.get_dummy_value()

    return sig, codegen


_y_transposed: Any = intrinsic(_y_transposed_typer)

#: LLVM fast-math flags of the reduced camera system's remaining scalar code (the right-hand side and a rig's
#: second-camera pairs; issue 15, branch lmsolve): reassociation and contraction fuse each a0 b0 + a1 b1 + a2 b2;
#: "nsz" ignores the sign of zero. No "nnan" / "ninf": a singular V + lam I must still give non-finite entries, which
#: the Cholesky kernel rejects (the LM then raises the damping).
_SCHUR_FASTMATH = {"reassoc", "contract", "nsz"}


#: S's 6x6 blocks while ba_reduced_system accumulates them: rows of 8 float64 (64 bytes, lanes 6 and 7 unused), each
#: block 6 rows, block (ca, cb) at (ca nc + cb) 48 doubles past a 64-byte boundary (_BLOCK_DOUBLES)
_BLOCK_DOUBLES = np.uint64(48)
_ROW_DOUBLES = np.uint64(8)


@numba.njit(cache=True, nogil=True, fastmath=_SCHUR_FASTMATH)
def ba_reduced_system(
    U: F64,
    V: F64,
    WT: F64,
    gc: F64,
    gp: F64,
    lam: float,
    c: I64,
    point_ptr: I64,
    point_obs: I64,
) -> tuple[F64, F64, F64]:  # pragma: no cover - compiled
    """Schur complement with damping lam: -> S (6 nc, 6 nc) = U + lam I - W (V + lam I)^-1 W^T (dense, its upper
    triangle only, which is all :func:`cholesky_solve_upper` reads: the strictly-lower off-diagonal blocks are left 0
    and the lower triangle of a diagonal block holds U + lam I less a rig's second-camera pairs only),
    rhs (6 nc,) = -gc + W (V + lam I)^-1 gp, and Vinv (npt, 3, 3). WT: each observation's W_e (6 x 3) transposed in
    rows of 8 lanes, C-contiguous (E, 3, 8), WT[e, k, i] = W_e[i, k] (lanes 6 and 7 read, never used: ba_linearize
    writes 0 there), as :func:`ba_linearize` returns it.

    point_obs[point_ptr[q]:point_ptr[q + 1]] lists the observations of free point q whose pose is free.
    Per point, each observation's Y_a^T = (W_a (V + lam I)^-1)^T is formed in 8-lane rows (scratch YT: (n, 3, 8)) from
    WT's rows (read in place: until branch lmcpu23 each W_a was transposed into a scratch here, per LM trial), and each
    pair (a <= b) updates its 6x6 block of S one 8-lane row at a time (the SIMD intrinsics
    above): the block Y_a W_b^T goes to the upper triangle (its transpose W_b Y_a^T when ca > cb), a point's own
    diagonal block gets its upper triangle. Every entry of S receives the products over k = 0, 1, 2 of one pair,
    fused, one point after the other.

    The blocks are accumulated in a scratch of 64-byte rows (block (ca, cb) = 6 rows of 8 lanes, aligned to 64
    bytes: no row straddles two cache lines, a block is 6 consecutive lines) and copied into the dense S at the end:
    the same operations on every entry in the same order as accumulating in the dense matrix (branch lmcost3:
    0.87x the dense accumulation's CPU on captured fr1 local BAs, S, rhs and Vinv equal to the bit).
    """
    nc = U.shape[0]
    npt = V.shape[0]
    n6 = 6 * nc
    unc = np.uint64(nc)
    Sb = np.zeros(nc * nc * 48 + 8)  # the blocks (+ 8: room to start at a 64-byte boundary)
    base = np.uint64(((64 - Sb.ctypes.data % 64) % 64) // 8)
    rhs = np.zeros(n6)
    Vinv = np.zeros((npt, 3, 3))
    for q in range(nc):
        o = base + (np.uint64(q) * unc + np.uint64(q)) * _BLOCK_DOUBLES
        for i in range(6):
            rhs[6 * q + i] = -gc[q, i]
            for jj in range(6):
                Sb[o + np.uint64(8 * i + jj)] = U[q, i, jj]
            Sb[o + np.uint64(9 * i)] += lam
    Vd = np.zeros((3, 3))
    YT = np.zeros((64, 3, 8))  # YT[a, k, i] = Y_a[i, k], Y_a = W_a (V + lam I)^-1 of the point's observations
    cs = np.zeros(64, np.uint64)  # free pose index of each observation (unsigned: see _U6)
    es = np.zeros(64, np.int64)  # the observation (row of W)
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
            cs = np.zeros(n, np.uint64)
            es = np.zeros(n, np.int64)
        for a in range(n):
            e = point_obs[start + a]
            es[a] = e
            cs[a] = np.uint64(c[e])
            _y_transposed(YT, 24 * a, WT, 24 * e, Vinv, 9 * q)
            ca = c[e]
            for i in range(6):
                rhs[6 * ca + i] += YT[a, 0, i] * gp[q, 0] + YT[a, 1, i] * gp[q, 1] + YT[a, 2, i] * gp[q, 2]
        for a in range(n):
            ca = cs[a]
            for b in range(a, n):
                cb = cs[b]
                if ca < cb:  # block (ca, cb)[i, jj] -= Y_a[i] . W_b[jj]
                    _sub_block_yw(Sb, base + (ca * unc + cb) * _BLOCK_DOUBLES, _ROW_DOUBLES, YT, 24 * a, WT, 24 * es[b])
                elif ca > cb:  # block (cb, ca)[jj, i] -= W_b[jj] . Y_a[i]
                    _sub_block_wy(Sb, base + (cb * unc + ca) * _BLOCK_DOUBLES, _ROW_DOUBLES, WT, 24 * es[b], YT, 24 * a)
                elif a == b:  # the point's own diagonal block: its upper triangle (the Cholesky kernel reads no other)
                    _sub_block_diag(
                        Sb, base + (ca * unc + ca) * _BLOCK_DOUBLES, _ROW_DOUBLES, YT, 24 * a, WT, 24 * es[b]
                    )
                else:  # one keyframe observes the point twice (a rig's second camera): both halves of the block
                    eb = es[b]
                    o = base + (ca * unc + ca) * _BLOCK_DOUBLES
                    for i in range(6):
                        for jj in range(6):
                            v = YT[a, 0, i] * WT[eb, 0, jj] + YT[a, 1, i] * WT[eb, 1, jj] + YT[a, 2, i] * WT[eb, 2, jj]
                            Sb[o + np.uint64(8 * i + jj)] -= v
                            Sb[o + np.uint64(8 * jj + i)] -= v
    S = np.zeros((n6, n6))
    for ca in range(nc):  # the blocks on and above the diagonal into the dense matrix (the others stay 0)
        for cb in range(ca, nc):
            o = base + (np.uint64(ca) * unc + np.uint64(cb)) * _BLOCK_DOUBLES
            for i in range(6):
                for jj in range(6):
                    S[6 * ca + i, 6 * cb + jj] = Sb[o + np.uint64(8 * i + jj)]
    return S, rhs, Vinv


@numba.njit(cache=True, nogil=True)
def cholesky_solve_upper(S: F64, rhs: F64) -> F64:  # pragma: no cover - compiled
    """Solve S x = rhs for a symmetric positive-definite S (n, n) given by its upper triangle (the lower one
    is never read): S = R^T R with R upper triangular, factored on a copy row by row, each update a contiguous
    row operation that skips zero multipliers (so the zero blocks of a sparse reduced camera system cost
    nothing). Returns x, or NaN everywhere when a pivot is not positive (the LM driver then raises the damping).

    Single-threaded and GIL-free on purpose: a multithreaded BLAS Cholesky of these small systems oversubscribes
    the cores that tracking needs (and was 100x slower than this on a loaded 2-core machine).
    """
    n = S.shape[0]
    un = np.uint64(n)
    R = S.copy()
    x = rhs.copy()
    for j in range(n):
        d = R[j, j]
        if not d > 0.0:  # also NaN
            return np.full(n, np.nan)
        d = np.sqrt(d)
        R[j, j] = d
        inv = 1.0 / d
        for k in range(np.uint64(j + 1), un):
            R[j, k] *= inv
        for i in range(j + 1, n):
            f = R[j, i]
            if f != 0.0:
                for k in range(np.uint64(i), un):  # unsigned: no wraparound test, so LLVM vectorizes the row update
                    R[i, k] -= f * R[j, k]
    for j in range(n):  # R^T y = rhs
        x[j] /= R[j, j]
        xj = x[j]
        for k in range(j + 1, n):
            x[k] -= R[j, k] * xj
    for j in range(n - 1, -1, -1):  # R x = y
        s = x[j]
        for k in range(j + 1, n):
            s -= R[j, k] * x[k]
        x[j] = s / R[j, j]
    return x


@numba.njit(cache=True, nogil=True)
def ba_back_substitute(
    dc: F64, Vinv: F64, WT: F64, gp: F64, c: I64, point_ptr: I64, point_obs: I64
) -> F64:  # pragma: no cover - compiled
    """dp (npt, 3) = Vinv_q (-gp_q - sum_e W_e^T dc_(c_e)) over the observations of each free point (WT (E, 3, 8):
    W_e transposed, :func:`ba_linearize`'s layout; row i of W_e^T is WT[e, i, :6])."""
    npt = Vinv.shape[0]
    dp = np.zeros((npt, 3))
    t = np.zeros(3)
    for q in range(npt):
        for i in range(3):
            t[i] = -gp[q, i]
        for a in range(point_ptr[q], point_ptr[q + 1]):
            e = point_obs[a]
            base = 6 * c[e]
            for i in range(3):
                s = 0.0
                for k in range(6):
                    s += WT[e, i, k] * dc[base + k]
                t[i] -= s
        for i in range(3):
            dp[q, i] = Vinv[q, i, 0] * t[0] + Vinv[q, i, 1] * t[1] + Vinv[q, i, 2] * t[2]
    return dp


@numba.njit(cache=True, nogil=True)
def ba_solve_dense(
    U: F64, V: F64, WT: F64, gc: F64, gp: F64, lam: float, c: I64, point_ptr: I64, point_obs: I64
) -> F64:  # pragma: no cover - compiled
    """The LM's damped step through the dense Schur complement in one compiled call (BundleSolver.solve):
    :func:`ba_reduced_system`, :func:`cholesky_solve_upper`, :func:`ba_back_substitute`, -> h (6 nc + 3 npt,) =
    [dc (6 nc,): the free poses' [omega (rad), v (m)], dp (3 npt,): the free points' m], or NaN everywhere when dc
    is not finite (a pivot not positive, or a non-finite V^-1 / rhs: the LM then raises the damping).

    The same three kernels on the same arrays as calling them one by one from Python and concatenating dc and dp,
    so h is theirs bit for bit (each keeps its own compile flags: the reduced system's fast-math flags are on its
    instructions); what goes is the Python between them (three dispatches of nine array arguments, the finiteness
    test's numpy calls, the concatenation) once per LM trial."""
    S, rhs, Vinv = ba_reduced_system(U, V, WT, gc, gp, lam, c, point_ptr, point_obs)
    dc = cholesky_solve_upper(S, rhs)
    n = dc.shape[0]
    npt = Vinv.shape[0]
    for i in range(n):
        if not np.isfinite(dc[i]):
            return np.full(n + 3 * npt, np.nan)
    dp = ba_back_substitute(dc, Vinv, WT, gp, c, point_ptr, point_obs)
    h = np.empty(n + 3 * npt)
    h[:n] = dc
    h[n:] = dp.ravel()
    return h


@numba.njit(cache=True, nogil=True)
def ba_retract(T: F64, X: F64, free_poses: I64, free_points: I64, h: F64) -> tuple[F64, F64]:  # pragma: no cover
    """The LM's retraction in one compiled pass (slamkit_scipy.bundle's BundleSolver.retract):
    T (K, 4, 4) poses T_c_w, X (M, 3) points (m), h = [xi_0, .., xi_(nc-1), dp_0, .., dp_(np-1)] with xi = [omega
    (rad), v (m)] per free pose (left perturbation T <- exp(xi) T: slamkit.geometry.se3_kernels.se3_exp_times, the
    kernel tracking's pose optimization retracts with; its docstring has the formula and the small-angle series)
    and dp (m) per free point (X <- X + dp). -> new (K, 4, 4) and (M, 3) arrays; the last row of the poses and
    the fixed poses and points are copied, the inputs are not written."""
    Tn = T.copy()
    Xn = X.copy()
    for q in range(free_poses.shape[0]):
        k = free_poses[q]
        Tn[k, :3, :] = se3_exp_times(h[6 * q : 6 * q + 6], T[k])[:3, :]
    base = 6 * free_poses.shape[0]
    for q in range(free_points.shape[0]):
        j = free_points[q]
        for i in range(3):
            Xn[j, i] = X[j, i] + h[base + 3 * q + i]
    return Tn, Xn


@numba.njit(cache=True, nogil=True)
def ba_cost(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
    delta: F64,
    robust: bool,
    cam: F64,
    fisheye: bool,
) -> float:  # pragma: no cover - compiled
    """Sum over observations of rho(chi2) (Huber when ``robust``, else chi2): the cost ba_linearize returns."""
    cost = 0.0
    for e in range(obs_pose.shape[0]):
        k = obs_pose[e]
        j = obs_point[e]
        x = R[k, 0, 0] * X[j, 0] + R[k, 0, 1] * X[j, 1] + R[k, 0, 2] * X[j, 2] + t[k, 0]
        y = R[k, 1, 0] * X[j, 0] + R[k, 1, 1] * X[j, 1] + R[k, 1, 2] * X[j, 2] + t[k, 1]
        z = R[k, 2, 0] * X[j, 0] + R[k, 2, 1] * X[j, 1] + R[k, 2, 2] * X[j, 2] + t[k, 2]
        iz = 1.0 / z
        if fisheye:
            u, v = kb_project(x, y, z, cam[e])
            r0 = u - uvr[e, 0]
            r1 = v - uvr[e, 1]
        else:
            u = intr[e, 0] * x * iz + intr[e, 2]
            r0 = u - uvr[e, 0]
            r1 = intr[e, 1] * y * iz + intr[e, 3] - uvr[e, 1]
        chi2 = r0 * r0 + r1 * r1
        if stereo[e]:
            r2 = u - bf[e] * iz - uvr[e, 2]
            chi2 += r2 * r2
        chi2 *= info[e]
        d = delta[e]
        if robust and chi2 > d * d:
            cost += 2.0 * d * np.sqrt(chi2) - d * d
        else:
            cost += chi2
    return cost


@numba.njit(cache=True, nogil=True)
def kb_jacobians(p_c: F64, cam: F64) -> F64:  # pragma: no cover - compiled
    """(E, 2, 3) d (u, v) / d p_c of Kannala-Brandt observations: p_c (E, 3) camera points, cam (E, 8)."""
    A = np.empty((p_c.shape[0], 2, 3))
    for e in range(p_c.shape[0]):
        kb_jacobian(p_c[e, 0], p_c[e, 1], p_c[e, 2], cam[e], A[e])
    return A


@numba.njit(cache=True, nogil=True)
def ba_chi2_depth(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """(E,) chi2 and (E,) depth (m, the camera z) of every pinhole observation: the arithmetic of
    slamkit_scipy.reprojection's residuals / chi2_of on slamkit_scipy.bundle's camera points, term by term in the same
    order (p_c = R X + t; u = fx x / z + cx, r = (u - u_obs, fy y / z + cy - v_obs, u - bf / z - u_right_obs or 0);
    chi2 = info |r|^2), without the (E, 4, 4) pose gather and the temporaries. numpy's einsum sums a 3-term product
    as (p0 + p2) + p1 (its unrolled contiguous loop): the rotations and |r|^2 are summed in that order here, so the
    results are those of the numpy path to the bit (tests/unit/scipy_backend/test_ba_kernels.py)."""
    E = obs_pose.shape[0]
    chi2 = np.empty(E)
    depth = np.empty(E)
    for e in range(E):
        k = obs_pose[e]
        j = obs_point[e]
        x = (R[k, 0, 0] * X[j, 0] + R[k, 0, 2] * X[j, 2]) + R[k, 0, 1] * X[j, 1] + t[k, 0]
        y = (R[k, 1, 0] * X[j, 0] + R[k, 1, 2] * X[j, 2]) + R[k, 1, 1] * X[j, 1] + t[k, 1]
        z = (R[k, 2, 0] * X[j, 0] + R[k, 2, 2] * X[j, 2]) + R[k, 2, 1] * X[j, 1] + t[k, 2]
        iz = 1.0 / z
        u = intr[e, 0] * x * iz + intr[e, 2]
        r0 = u - uvr[e, 0]
        r1 = intr[e, 1] * y * iz + intr[e, 3] - uvr[e, 1]
        r2 = 0.0
        if stereo[e]:
            r2 = u - bf[e] * iz - uvr[e, 2]
        chi2[e] = info[e] * ((r0 * r0 + r2 * r2) + r1 * r1)
        depth[e] = z
    return chi2, depth
