"""Rendering of a scene of textured rectangles through a pinhole camera: images, exact depth, plane ids.

Per visible rectangle (front-facing, in front of the near plane, overlapping the image):

1. clip its polygon against the near plane and project it to get a pixel bounding box (the ROI);
2. in one compiled, GIL-free pass over the ROI (``_draw_plane``): per pixel, the inverse homography G = H^-1 of
   the texture-to-image homography H = K [R | t] A (A maps texel coordinates to homogeneous world points of the
   rectangle) gives the texel the pixel centre's ray hits and, in its third row, the inverse depth 1/z (affine in
   pixel coordinates for a plane); keep the pixel if the texel lies on the rectangle and z beats the z-buffer, and
   only then sample the texture there (bilinear; see "Sampling" below).

Sampling. The grey value of a kept pixel is, bit for bit, what ``cv2.warpPerspective(level texture, H_roi, ROI
size, INTER_LINEAR, BORDER_REPLICATE)`` gives at that ROI pixel with OpenCV 5.0's AVX2 kernel (the renderer's
previous method, which warped the whole ROI once per mip level and then kept a third of the pixels): M = the
float32 cast of cv2.invert(H_roi); for ROI columns c < 16 floor(w / 16) (the vector body) sx = fma(M0, c, r M1 +
M2) / fma(M6, c, r M7 + M8), for the last w mod 16 columns (the scalar tail) sx = (fma(c, M0, r M1) + M2) /
(fma(c, M6, r M7) + M8) (sy likewise), all in float32; the four neighbours (clamped to the texture) are mixed with
float32 fmas and rounded half to even. Sampling only the kept pixels, once, is what makes a frame cheap; the
identity with the old images (and so with the sequential runner's trajectories) is tested against the cv2 path,
which the colour image still uses (``_warp`` + ``_composite``), and against stored checksums. The grey image is
now this module's arithmetic on any machine; the cv2 path's depends on OpenCV's version and SIMD dispatch (16
columns per vector step is AVX2's; an SSE4.1-only or another OpenCV build would give other last bits), so the
test against it is the one that notices when the two part.

Depth is the exact z of the ray-plane intersection at each pixel centre (OpenCV convention: pixel (0, 0)
has its centre at (0, 0)), in float32 metres. Anti-aliasing: a texture is mip-mapped (levels 2x smaller
each) and each pixel takes the level matching its footprint, log2 of sqrt(|det dtexel/dpixel|), which for
a plane is |det G| z^3; a rectangle spanning several levels samples each pixel in the level of its depth band.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, types
from numba.extending import intrinsic
from numpy.typing import NDArray
from scipy.special import ndtri

from slamkit.io.synthetic.scenes import Plane, Scene
from slamkit.io.synthetic.textures import TextureBank

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]

# Number of mip levels (level l is 2^l times coarser). 6 levels reach 1/32: enough for a wall 25 m away
# at fx ~ 460 px with 256 texels/m. Texture sizes are rounded up to multiples of 2^(levels-1).
MIP_LEVELS = 6
# Near clipping distance, m: nothing closer to the camera is drawn.
NEAR_M = 0.05


@dataclass(frozen=True)
class RenderPlane:
    """A scene rectangle prepared for rendering.

    A_w: (4, 3) maps level-0 texel coordinates (s, t, 1) (texel centres at integers) to homogeneous world
    points; the texture covers the rectangle exactly. corners_w: (4, 3) m. normal_w: (3,) towards the
    visible side.
    """

    index: int
    plane: Plane
    width_px: int
    height_px: int
    texels_per_m: float
    A_w: F64
    corners_w: F64
    normal_w: F64


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view. grey: (H, W) uint8; color: (H, W, 3) uint8 BGR; depth_m: (H, W) float32, z along
    the optical axis, 0 where no surface; labels: (H, W) int32 index of the scene plane seen, -1 for none."""

    grey: U8 | None
    color: U8 | None
    depth_m: F32
    labels: I32 | None


def _round_up(x: float, multiple: int) -> int:
    return max(multiple, math.ceil(x / multiple - 1e-9) * multiple)


def prepare_planes(scene: Scene) -> list[RenderPlane]:
    """Texture sizes and texel-to-world maps of every plane of ``scene``."""
    out = []
    granule = 2 ** (MIP_LEVELS - 1)
    for i, p in enumerate(scene.planes):
        o, u, v = (np.asarray(a, dtype=np.float64) for a in (p.origin_m, p.u_m, p.v_m))
        w = _round_up(float(np.linalg.norm(u)) * scene.texels_per_m, granule)
        h = _round_up(float(np.linalg.norm(v)) * scene.texels_per_m, granule)
        A = np.zeros((4, 3))
        A[:3, 0], A[:3, 1] = u / w, v / h
        A[:3, 2] = o + 0.5 * u / w + 0.5 * v / h  # texel (0, 0) is the centre of the first texel
        A[3, 2] = 1.0
        out.append(RenderPlane(i, p, w, h, scene.texels_per_m, A, p.corners_m, p.normal))
    return out


def _clip_near(poly_c: F64, near: float) -> F64:
    """Sutherland-Hodgman clip of a convex polygon (N, 3) (camera frame) to z >= near; (M, 3), maybe M=0."""
    if bool((poly_c[:, 2] >= near).all()):  # nothing to clip: the loop below would return the same points
        return poly_c
    out = []
    n = poly_c.shape[0]
    for i in range(n):
        a, b = poly_c[i], poly_c[(i + 1) % n]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


@njit(cache=True, nogil=True)
def _composite(  # pragma: no cover - compiled
    G: F64,
    x0: int,
    y0: int,
    h: int,
    w: int,
    s_max: float,
    t_max: float,
    z_lo: float,
    z_hi: float,
    zbuf: F32,
    label: int,
    labels: I32,
    src_g: U8,
    dst_g: U8,
    src_c: U8,
    dst_c: U8,
) -> None:
    """Z-buffer one rectangle's ROI into the frame (in place).

    G: (3, 3) image pixel -> homogeneous level-0 texel, third component = 1/z. The ROI is h x w px with
    top-left pixel (x0, y0); src_* are the warped ROI images (h, w[, 3]); empty arrays switch an output off. Pixels
    with z in [z_lo, z_hi) whose texel is on the rectangle (-0.5 <= s <= s_max, same for t) and which
    are nearer than zbuf are written.
    """
    use_g, use_c, use_l = src_g.size > 0, src_c.size > 0, labels.size > 0
    for r in range(h):
        y = y0 + r
        ws = G[2, 1] * y + G[2, 2]
        ss = G[0, 1] * y + G[0, 2]
        ts = G[1, 1] * y + G[1, 2]
        for c in range(w):
            x = x0 + c
            inv_z = G[2, 0] * x + ws
            if inv_z <= 0.0:
                continue
            z = 1.0 / inv_z
            if z < z_lo or z >= z_hi or z >= zbuf[y, x]:
                continue
            s = (G[0, 0] * x + ss) * z
            t = (G[1, 0] * x + ts) * z
            if s < -0.5 or s > s_max or t < -0.5 or t > t_max:
                continue
            zbuf[y, x] = z
            if use_l:
                labels[y, x] = label
            if use_g:
                dst_g[y, x] = src_g[r, c]
            if use_c:
                dst_c[y, x, 0] = src_c[r, c, 0]
                dst_c[y, x, 1] = src_c[r, c, 1]
                dst_c[y, x, 2] = src_c[r, c, 2]


def _fma32_typing(typingctx, a, b, c):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Typing of ``_fma32``: float32 (a, b, c) -> float32, lowered to LLVM's llvm.fma.f32."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.fma(*args)

    return sig, codegen


#: Fused multiply-add a * b + c of three float32 values with one rounding, as the FMA instructions of OpenCV's
#: SIMD warp kernels (callable from compiled code only).
_fma32: Callable[[np.float32, np.float32, np.float32], np.float32] = intrinsic(_fma32_typing)  # type: ignore[assignment]


@njit(cache=True, nogil=True, error_model="numpy")
def _depth_test(  # pragma: no cover - compiled
    G: F64,
    x0: int,
    y: int,
    w: int,
    s_max: float,
    t_max: float,
    z_near: float,
    zrow: F32,
    zs: F64,
    keep: NDArray[np.bool_],
) -> None:
    """Row y, columns x0 .. x0 + w - 1 of a rectangle: zs[c] = the depth z (m) of the ray through pixel (x0 + c, y)
    on its plane (G (3, 3): image pixel -> homogeneous level-0 texel, third component 1/z) and keep[c] = whether
    the pixel shows it: 1/z > 0, z >= z_near, z nearer than zrow[x0 + c] (the z-buffer's row) and the texel on the
    rectangle (-0.5 <= s <= s_max, same for t). Branch-free, so it vectorizes; the same comparisons as a
    short-circuit test (NaN compares false either way)."""
    gx, gy, gw = G[0, 0], G[1, 0], G[2, 0]
    ws = G[2, 1] * y + G[2, 2]
    ss = G[0, 1] * y + G[0, 2]
    ts = G[1, 1] * y + G[1, 2]
    for c in range(w):
        x = x0 + c
        inv_z = gw * x + ws
        z = 1.0 / inv_z
        s = (gx * x + ss) * z
        t = (gy * x + ts) * z
        zs[c] = z
        keep[c] = (
            not (inv_z <= 0.0)
            and not (z < z_near)
            and not (z >= zrow[x])
            and not (s < -0.5)
            and not (s > s_max)
            and not (t < -0.5)
            and not (t > t_max)
        )


@njit(cache=True, nogil=True, error_model="numpy")
def _texel_coords(  # pragma: no cover - compiled
    M: F32,
    tail: bool,
    r: int,
    cols: I32,
    j0: int,
    j1: int,
    base: int,
    tw: int,
    th: int,
    i00: I32,
    i01: I32,
    i10: I32,
    i11: I32,
    ax: F32,
    ay: F32,
) -> None:
    """For ROI pixels (cols[j], r), j0 <= j < j1: the texel that M (9,) float32 (ROI pixel -> texel of a (th, tw)
    texture stored at ``base`` in a flat buffer) maps each to, with OpenCV 5.0 warpPerspective's float32 arithmetic
    (module docstring; ``tail``: the columns of its scalar tail). Writes the flat indices of the four neighbours,
    clamped to the texture (BORDER_REPLICATE): i00[j], i01[j] (row floor(sy), columns floor(sx) and floor(sx) + 1),
    i10[j], i11[j] likewise for row floor(sy) + 1 (four arrays: stores into one would not vectorize); and the weights ax[j], ay[j] = the fractional parts.
    ``error_model="numpy"`` (IEEE division, no zero check) lets the loop vectorize."""
    yf = np.float32(r)
    lo = np.float32(-4.0)
    hi_x = np.float32(tw + 4)
    hi_y = np.float32(th + 4)
    # 32-bit integer arithmetic vectorizes (64-bit multiplies do not, on AVX2); the pyramids are < 2^31 texels
    tw32, th32, base32 = np.int32(tw), np.int32(th), np.int32(base)
    zero, one = np.int32(0), np.int32(1)
    # M's entries as locals: loop invariants the vectorizer need not reload (M could alias the outputs)
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = M[0], M[1], M[2], M[3], M[4], M[5], M[6], M[7], M[8]
    if tail:  # the scalar tail: (fma(x, M0, y M1) + M2) / (fma(x, M6, y M7) + M8)
        bx, by, bw = yf * m1, yf * m4, yf * m7
        a0, a3, a6 = m2, m5, m8
    else:  # the vector body: fma(M0, x, y M1 + M2) / fma(M6, x, y M7 + M8)
        bx, by, bw = yf * m1 + m2, yf * m4 + m5, yf * m7 + m8
        a0 = a3 = a6 = np.float32(0.0)
    for j in range(j0, j1):
        xf = np.float32(cols[j])
        # fma(a, b, c) is symmetric in a and b, so the tail's fma(x, M0, .) is fma(M0, x, .); adding 0.0 to
        # the body's fma leaves it unchanged (x + 0.0 == x for every x but -0.0, and sx = -0.0 and 0.0 give
        # the same texel and weight)
        sw = _fma32(m6, xf, bw) + a6
        sx = (_fma32(m0, xf, bx) + a0) / sw
        sy = (_fma32(m3, xf, by) + a3) / sw
        # a kept pixel's texel is within half a texel of the texture; the clamps only guard the integer
        # conversion (beyond the border both neighbours are the border texel, whatever the weight)
        sx = min(max(sx, lo), hi_x)
        sy = min(max(sy, lo), hi_y)
        fx = np.floor(sx)
        fy = np.floor(sy)
        ix = np.int32(fx)
        iy = np.int32(fy)
        ax[j] = sx - fx
        ay[j] = sy - fy
        xa = min(max(ix, zero), tw32 - one)
        xb = min(max(ix + one, zero), tw32 - one)
        ya = base32 + min(max(iy, zero), th32 - one) * tw32
        yb = base32 + min(max(iy + one, zero), th32 - one) * tw32
        i00[j] = ya + xa
        i01[j] = ya + xb
        i10[j] = yb + xa
        i11[j] = yb + xb


@njit(cache=True, nogil=True, error_model="numpy")
def _bilinear(  # pragma: no cover - compiled
    flat: U8,
    n: int,
    i00: I32,
    i01: I32,
    i10: I32,
    i11: I32,
    ax: F32,
    ay: F32,
    p00: F32,
    p01: F32,
    p10: F32,
    p11: F32,
    vals: U8,
) -> None:
    """vals[j] for j < n: the neighbours at the flat indices ``_texel_coords`` wrote mixed with float32 fmas
    (along x, then y, as cv2's v_fma), rounded half to even and saturated to uint8; p00..p11 (n,) float32 scratch."""
    # the byte loads first (a loop of its own: gathers of bytes do not vectorize), then the arithmetic, which does
    for j in range(n):
        p00[j] = flat[i00[j]]
        p01[j] = flat[i01[j]]
        p10[j] = flat[i10[j]]
        p11[j] = flat[i11[j]]
    for j in range(n):
        f0 = _fma32(ax[j], p01[j] - p00[j], p00[j])
        f1 = _fma32(ax[j], p11[j] - p10[j], p10[j])
        v = np.rint(_fma32(ay[j], f1 - f0, f0))
        vals[j] = np.uint8(min(max(v, np.float32(0.0)), np.float32(255.0)))


@njit(cache=True, nogil=True, error_model="numpy")
def _draw_plane(  # pragma: no cover - compiled
    G: F64,
    x0: int,
    y0: int,
    h: int,
    w: int,
    s_max: float,
    t_max: float,
    z_near: float,
    z_bounds: F64,
    flat: U8,
    offsets: I64,
    dims: I64,
    Ms: F32,
    zbuf: F32,
    label: int,
    labels: I32,
    dst_g: U8,
) -> None:
    """Z-buffer one rectangle's ROI into the frame (in place), sampling its texture only where a pixel is kept.

    G: (3, 3) image pixel -> homogeneous level-0 texel, third component = 1/z. The ROI is h x w px with top-left
    pixel (x0, y0). Mip levels: the plane uses L consecutive levels; z_bounds (L - 1,) ascending depths (m) where
    the level steps up (a pixel at depth z takes the k-th of them, k = number of bounds <= z); level k's texture
    is dims[k] = (height, width) texels at flat[offsets[k]:] and Ms[k] (9,) float32 maps ROI pixels to its texels.
    Pixels with z >= z_near whose texel is on the rectangle (-0.5 <= s <= s_max, same for t) and which are nearer
    than zbuf are written: zbuf, labels (if not empty), dst_g (if not empty).
    """
    use_g, use_l = dst_g.size > 0, labels.size > 0
    n_bounds = z_bounds.shape[0]
    n_body = (w // 16) * 16
    # per row: the kept pixels' columns (ROI) and levels, their texel indices, weights and values
    cols = np.empty(w, dtype=np.int32)
    levs = np.empty(w, dtype=np.int64)
    i00 = np.empty(w, dtype=np.int32)
    i01 = np.empty(w, dtype=np.int32)
    i10 = np.empty(w, dtype=np.int32)
    i11 = np.empty(w, dtype=np.int32)
    ax = np.empty(w, dtype=np.float32)
    ay = np.empty(w, dtype=np.float32)
    vals = np.empty(w, dtype=np.uint8)
    p00 = np.empty(w, dtype=np.float32)
    p01 = np.empty(w, dtype=np.float32)
    p10 = np.empty(w, dtype=np.float32)
    p11 = np.empty(w, dtype=np.float32)
    zs = np.empty(w, dtype=np.float64)
    keep = np.empty(w, dtype=np.bool_)
    for r in range(h):
        y = y0 + r
        _depth_test(G, x0, y, w, s_max, t_max, z_near, zbuf[y], zs, keep)
        n = 0
        for c in range(w):
            if not keep[c]:
                continue
            z = zs[c]
            zbuf[y, x0 + c] = z
            if use_l:
                labels[y, x0 + c] = label
            if use_g:
                k = 0
                while k < n_bounds and z >= z_bounds[k]:
                    k += 1
                cols[n] = c
                levs[n] = k
                n += 1
        if n == 0:
            continue
        # Sample the kept pixels' texels: per run of one level and one side of the body / tail border, the
        # coordinates in a loop the compiler vectorizes, then the bilinear mix.
        j0 = 0
        while j0 < n:
            k = levs[j0]
            tail = cols[j0] >= n_body
            j1 = j0 + 1
            while j1 < n and levs[j1] == k and (cols[j1] >= n_body) == tail:
                j1 += 1
            _texel_coords(Ms[k], tail, r, cols, j0, j1, offsets[k], dims[k, 1], dims[k, 0], i00, i01, i10, i11, ax, ay)
            j0 = j1
        _bilinear(flat, n, i00, i01, i10, i11, ax, ay, p00, p01, p10, p11, vals)
        for j in range(n):
            dst_g[y, x0 + cols[j]] = vals[j]


@njit(cache=True, nogil=True)
def _add_noise(image: U8, index: NDArray[np.uint16], table: NDArray[np.int16], out: U8) -> None:  # pragma: no cover
    """out = clip(image + table[index], 0, 255) element-wise on flat (N,) arrays, the sum in int16 as NumPy's."""
    for i in range(image.shape[0]):
        v = np.int16(np.int16(image[i]) + table[index[i]])
        out[i] = 0 if v < 0 else (255 if v > 255 else v)


def _warp(texture: U8, H: F64, size: tuple[int, int]) -> U8:
    """texture warped by homography H (texel -> ROI pixel) into a (size[1], size[0]) ROI, bilinear; texels
    just outside the texture repeat its border (pixels there are dropped by the coverage test anyway)."""
    out = cv2.warpPerspective(texture, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.uint8)


_EMPTY_G = np.zeros((0, 0), dtype=np.uint8)
_EMPTY_C = np.zeros((0, 0, 3), dtype=np.uint8)
_EMPTY_L = np.zeros((0, 0), dtype=np.int32)
_EMPTY_FLAT = np.zeros(0, dtype=np.uint8)
_NO_LEVEL = np.zeros(0, dtype=np.int64)
_NO_DIMS = np.zeros((0, 2), dtype=np.int64)


class PlaneRenderer:
    """Renders a scene through a pinhole camera K (3, 3) of ``width`` x ``height`` px (no distortion).

    Textures come from ``bank`` (generated on first sight, then cached). Not thread-safe: use one renderer
    per thread. ``legacy_cv2``: draw every image by the cv2 path (whole-ROI warps per mip level), which the
    sampled path reproduces byte for byte at a fraction of the CPU; kept as the reference the tests compare with.
    """

    def __init__(
        self, scene: Scene, bank: TextureBank, K: F64, width: int, height: int, legacy_cv2: bool = False
    ) -> None:
        self.scene = scene
        self.bank = bank
        self.K = np.asarray(K, dtype=np.float64)
        self.width, self.height = int(width), int(height)
        self.planes = prepare_planes(scene)
        self.legacy_cv2 = bool(legacy_cv2)
        self._packed_grey: dict[int, tuple[U8, I64, I64]] = {}

    def prepare_textures(self, grey: bool = True, color: bool = False) -> None:
        """Generate every plane's texture pyramids now (else each is made the first time its plane shows:
        0.9 s for the room's 35 planes, 2.8 s for long_loop's 116, in bursts during playback)."""
        for rp in self.planes:
            for colour in [c for c, wanted in ((False, grey), (True, color)) if wanted]:
                self.bank.get(rp.plane.texture, rp.width_px, rp.height_px, rp.texels_per_m, colour)
            if grey:
                self._packed(rp)

    def _visible(self, T_c_w: F64) -> list[tuple[RenderPlane, F64, F64]]:
        """(plane, clipped polygon in camera frame (M, 3), its pixels (M, 2)) of planes that may show."""
        R, t = T_c_w[:3, :3], T_c_w[:3, 3]
        centre_w = -R.T @ t
        out = []
        for rp in self.planes:
            if np.dot(centre_w - rp.corners_w[0], rp.normal_w) <= 1e-9:  # seen from behind or edge-on
                continue
            poly = _clip_near(rp.corners_w @ R.T + t, NEAR_M)
            if poly.shape[0] < 3:
                continue
            uv = (poly[:, :2] / poly[:, 2:3]) * np.diag(self.K)[:2] + self.K[:2, 2]
            if (
                uv[:, 0].max() < -1
                or uv[:, 0].min() > self.width
                or uv[:, 1].max() < -1
                or uv[:, 1].min() > self.height
            ):
                continue
            out.append((rp, poly, uv))
        out.sort(key=lambda item: float(item[1][:, 2].min()))  # front to back: fewer overwrites
        return out

    def _packed(self, rp: RenderPlane) -> tuple[U8, I64, I64]:
        """The grey mip pyramid of plane ``rp`` in one buffer, for ``_draw_plane``: (flat texels, offsets (L,) of
        each level in it, dims (L, 2) = (height, width) of each level). Built on first use, then cached."""
        packed = self._packed_grey.get(rp.index)
        if packed is None:
            levels = self.bank.get(rp.plane.texture, rp.width_px, rp.height_px, rp.texels_per_m, False)
            sizes = [lv.size for lv in levels]
            offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
            dims = np.array([lv.shape[:2] for lv in levels], dtype=np.int64)
            flat = np.ascontiguousarray(np.concatenate([lv.ravel() for lv in levels]))
            packed = (flat, offsets, dims)
            self._packed_grey[rp.index] = packed
        return packed

    def render(self, T_w_c: F64, grey: bool = True, color: bool = False, labels: bool = False) -> RenderOutput:
        """Render the view of a camera at pose T_w_c (4, 4). Returns a RenderOutput (depth always).

        Without colour, each plane is drawn by one compiled pass that samples the texture only at the pixels it
        keeps (``_draw_plane``); with colour, by the cv2 path (whole-ROI warps per mip level, then
        ``_composite``), whose grey image is byte-identical to the other's."""
        T_c_w = np.linalg.inv(np.asarray(T_w_c, dtype=np.float64))
        H, W = self.height, self.width
        zbuf = np.full((H, W), np.inf, dtype=np.float32)
        img_g = np.zeros((H, W), dtype=np.uint8) if grey else _EMPTY_G
        img_c = np.zeros((H, W, 3), dtype=np.uint8) if color else _EMPTY_C
        lab = np.full((H, W), -1, dtype=np.int32) if labels else _EMPTY_L
        P = self.K @ T_c_w[:3, :]
        for rp, poly, uv in self._visible(T_c_w):
            if color or self.legacy_cv2:
                self._draw(rp, poly, uv, P, zbuf, lab, img_g if grey else None, img_c if color else None)
            else:
                self._draw_sampled(rp, poly, uv, P, zbuf, lab, img_g)
        zbuf[np.isinf(zbuf)] = 0.0
        return RenderOutput(img_g if grey else None, img_c if color else None, zbuf, lab if labels else None)

    def _setup(
        self, rp: RenderPlane, poly: F64, uv: F64, P: F64
    ) -> tuple[int, int, int, int, F64, F64, int, int, float] | None:
        """ROI (x0, y0, x1, y1) px, H0 (3, 3) level-0 texel -> image, G = H0^-1, the mip levels lvl_lo..lvl_hi the
        plane spans and lvl_offset (a pixel at depth z takes level lvl_offset + 1.5 log2 z); None if nothing
        shows."""
        x0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(uv[:, 0].max())) + 2, self.width)
        y1 = min(int(np.ceil(uv[:, 1].max())) + 2, self.height)
        if x1 <= x0 or y1 <= y0:
            return None
        H0 = P @ rp.A_w  # level-0 texel -> image, third row gives z
        det_H = float(np.linalg.det(H0))
        if not np.isfinite(det_H) or abs(det_H) < 1e-300:
            return None
        G = np.asarray(np.linalg.inv(H0), dtype=np.float64)
        # Mip level of a pixel at depth z: lvl_offset + 1.5 log2 z with lvl_offset = 0.5 log2|det G|.
        lvl_offset = 0.5 * math.log2(abs(float(np.linalg.det(G))))
        z_min, z_max = float(poly[:, 2].min()), float(poly[:, 2].max())
        lvl_lo = min(max(round(lvl_offset + 1.5 * math.log2(z_min)), 0), MIP_LEVELS - 1)
        lvl_hi = min(max(round(lvl_offset + 1.5 * math.log2(z_max)), 0), MIP_LEVELS - 1)
        return x0, y0, x1, y1, H0, G, lvl_lo, lvl_hi, lvl_offset

    @staticmethod
    def _roi_homography(H0: F64, x0: int, y0: int, level: int) -> F64:
        """(3, 3) level-``level`` texel -> ROI pixel (the ROI's top-left pixel is image pixel (x0, y0))."""
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        k = 2.0**level  # level-l texel s_l covers level-0 texels around 2^l (s_l + 0.5) - 0.5
        S = np.array([[k, 0.0, 0.5 * k - 0.5], [0.0, k, 0.5 * k - 0.5], [0.0, 0.0, 1.0]])
        return np.asarray(shift @ H0 @ S, dtype=np.float64)

    def _draw_sampled(self, rp: RenderPlane, poly: F64, uv: F64, P: F64, zbuf: F32, lab: I32, img_g: U8) -> None:
        """Draw plane ``rp`` by ``_draw_plane``: one pass over its ROI, sampling the texture at kept pixels only."""
        setup = self._setup(rp, poly, uv, P)
        if setup is None:
            return
        x0, y0, x1, y1, H0, G, lvl_lo, lvl_hi, lvl_offset = setup
        levels = range(lvl_lo, lvl_hi + 1)
        # The depths where the level steps up: lvl_offset + 1.5 log2 z = level - 0.5 (as _draw's bands).
        z_bounds = np.array([2.0 ** ((level - 0.5 - lvl_offset) / 1.5) for level in levels[1:]], dtype=np.float64)
        flat, offsets, dims = self._packed(rp) if img_g.size else (_EMPTY_FLAT, _NO_LEVEL, _NO_DIMS)
        Ms = np.zeros((len(levels), 9), dtype=np.float32)
        if img_g.size:
            for i, level in enumerate(levels):
                # cv2.warpPerspective inverts its matrix with cv2.invert (DECOMP_LU) and casts it to float32
                _, M = cv2.invert(self._roi_homography(H0, x0, y0, level))
                Ms[i] = np.asarray(M, dtype=np.float64).ravel()
            offsets, dims = offsets[lvl_lo : lvl_hi + 1], dims[lvl_lo : lvl_hi + 1]
        _draw_plane(
            G,
            x0,
            y0,
            y1 - y0,
            x1 - x0,
            rp.width_px - 0.5,
            rp.height_px - 0.5,
            NEAR_M,
            z_bounds,
            flat,
            offsets,
            dims,
            Ms,
            zbuf,
            rp.index,
            lab,
            img_g,
        )

    def _draw(
        self,
        rp: RenderPlane,
        poly: F64,
        uv: F64,
        P: F64,
        zbuf: F32,
        lab: I32,
        img_g: U8 | None,
        img_c: U8 | None,
    ) -> None:
        """Draw plane ``rp`` by the cv2 path: per mip level, warp the texture over the whole ROI
        (cv2.warpPerspective), then ``_composite`` the pixels of that level's depth band."""
        setup = self._setup(rp, poly, uv, P)
        if setup is None:
            return
        x0, y0, x1, y1, H0, G, lvl_lo, lvl_hi, lvl_offset = setup
        size = (x1 - x0, y1 - y0)
        s_max, t_max = rp.width_px - 0.5, rp.height_px - 0.5
        for level in range(lvl_lo, lvl_hi + 1):
            # The depths where the level changes: lvl_offset + 1.5 log2 z = level +- 0.5.
            z_lo = 0.0 if level == lvl_lo else 2.0 ** ((level - 0.5 - lvl_offset) / 1.5)
            z_hi = math.inf if level == lvl_hi else 2.0 ** ((level + 0.5 - lvl_offset) / 1.5)
            H_roi = self._roi_homography(H0, x0, y0, level)
            src_g, src_c = _EMPTY_G, _EMPTY_C
            if img_g is not None:
                tex = self.bank.get(rp.plane.texture, rp.width_px, rp.height_px, rp.texels_per_m, False)[level]
                src_g = _warp(tex, H_roi, size)
            if img_c is not None:
                tex = self.bank.get(rp.plane.texture, rp.width_px, rp.height_px, rp.texels_per_m, True)[level]
                src_c = _warp(tex, H_roi, size)
            _composite(
                G,
                x0,
                y0,
                y1 - y0,
                x1 - x0,
                s_max,
                t_max,
                max(z_lo, NEAR_M),
                z_hi,
                zbuf,
                rp.index,
                lab,
                src_g,
                img_g if img_g is not None else _EMPTY_G,
                src_c,
                img_c if img_c is not None else _EMPTY_C,
            )


class PixelNoise:
    """Zero-mean Gaussian pixel noise of std ``sigma`` grey levels, rounded to integers, added with clipping.

    Sampling goes through a table of the 65536 Gaussian quantiles (already multiplied by sigma and rounded)
    indexed by random 16-bit integers: the values follow N(0, sigma^2) rounded, truncated at +-4.3 sigma
    (probability 2e-5 beyond), and cost a third of drawing normal floats (pixel noise dominated the frame).
    """

    def __init__(self, sigma: float) -> None:
        self.sigma = float(sigma)
        quantiles = (np.arange(65536, dtype=np.float64) + 0.5) / 65536.0
        self._table = np.rint(ndtri(quantiles) * self.sigma).astype(np.int16)

    def apply(self, image: U8, rng: np.random.Generator) -> U8:
        """image: uint8 of any shape -> a new noisy uint8 image (``image`` itself when sigma is 0)."""
        if self.sigma <= 0:
            return image
        index = np.frombuffer(rng.bytes(2 * image.size), dtype=np.uint16)
        out = np.empty(image.shape, dtype=np.uint8)
        # one compiled, GIL-free pass; the same values as clip(image.astype(int16) + table[index], 0, 255)
        _add_noise(np.ascontiguousarray(image).reshape(-1), index, self._table, out.reshape(-1))
        return out
