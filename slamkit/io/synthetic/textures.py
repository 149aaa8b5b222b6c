"""Procedural, seeded textures for the synthetic world, and their mip-map pyramids.

A texture is a (H, W, 3) uint8 BGR image made of layers that give corners at every scale a SLAM front end
looks at: a two-colour low-frequency base, multi-octave value noise, and many random shapes (discs, rings,
ellipses, polygons, bars, glyphs, small checker and stripe patches) whose sizes are drawn log-uniformly in
metres, so the physical look does not depend on the texel density. Nothing repeats inside a texture; two
planes look alike only when a scene gives them the same texture key on purpose.

Determinism: the pixels are a pure function of (seed, key, size, texel density). Keys are hashed with
CRC-32 (Python's ``hash`` is salted per process and would break reproducibility).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]

# Shape sizes are drawn log-uniformly in this span (metres): 1.5 cm gives corners a few pixels wide at a
# few metres (fx ~ 460 px), 40 cm gives structure that survives the coarse levels of ORB's pyramid.
SHAPE_SIZE_RANGE_M = (0.015, 0.40)
# Shapes per square metre. With the size span above this covers each point ~2-3 times, so no area is
# left as bare noise (bare noise gives weak, unstable FAST corners).
SHAPES_PER_M2 = 140.0
# Value-noise octaves: (wavelength m, amplitude in grey levels). Low octaves shade, high ones add grain.
NOISE_OCTAVES_M = ((0.60, 40.0), (0.20, 28.0), (0.07, 18.0), (0.025, 10.0))
# Wavelength (m) of the field that mixes the two base colours of a texture.
BASE_MIX_WAVELENGTH_M = 1.2
# Half-width of a texture's hue family (OpenCV hue units, 0..180).
HUE_SPREAD = 22.0
# Glyphs for text shapes: letters and digits make distinctive, corner-rich blobs.
_GLYPHS = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#&%@"


def texture_rng(seed: int, key: str) -> np.random.Generator:
    """The generator of texture ``key`` under world ``seed``: stable across processes and platforms."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(key.encode("utf-8"))])


def _value_noise(rng: np.random.Generator, height: int, width: int, wavelength_px: float) -> F32:
    """(height, width) float32 smooth noise in about [-1, 1] with the given wavelength (bicubic lattice)."""
    step = max(wavelength_px, 1.0)
    gh, gw = math.ceil(height / step) + 3, math.ceil(width / step) + 3
    lattice = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    up = cv2.resize(lattice, (round(gw * step), round(gh * step)), interpolation=cv2.INTER_CUBIC)
    # Start one lattice cell in, away from the border effects of the resize.
    o = round(step)
    return np.ascontiguousarray(up[o : o + height, o : o + width])


def _random_colours(rng: np.random.Generator, n: int, hue: float, hue_spread: float) -> NDArray[np.int64]:
    """(n, 3) BGR colours around ``hue`` (OpenCV units, 0..180) +- hue_spread, each either dark or bright in
    *luminance* (what a grey image and FAST see), whatever its hue."""
    h = np.mod(hue + rng.uniform(-hue_spread, hue_spread, n), 180)
    sat = rng.uniform(40, 255, n)
    hsv = np.stack([h, sat, np.full(n, 255.0)], axis=1).astype(np.uint8)[None]
    bgr = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0].astype(np.float64)
    lum = bgr @ np.array([0.114, 0.587, 0.299])  # ITU-R BT.601 weights, as cv2.COLOR_BGR2GRAY
    target = np.where(rng.random(n) < 0.5, rng.uniform(10, 90, n), rng.uniform(160, 245, n))
    # Darken by scaling towards black, brighten by mixing towards white: both hit the target luminance.
    darker = bgr * (target / np.maximum(lum, 1e-6))[:, None]
    brighter = bgr + (255.0 - bgr) * ((target - lum) / np.maximum(255.0 - lum, 1e-6))[:, None]
    out = np.where((target < lum)[:, None], darker, brighter)
    return np.clip(np.round(out), 0, 255).astype(np.int64)


def _base_layer(rng: np.random.Generator, height: int, width: int, texels_per_m: float, hue: float) -> U8:
    """(H, W, 3) uint8: two base colours mixed by low-frequency noise, plus multi-octave grain.

    Computed at half resolution and upsampled: the finest octave is several texels long, so nothing is lost
    and the cost (the bulk of texture generation) drops fourfold.
    """
    h2, w2, tpm2 = (height + 1) // 2, (width + 1) // 2, texels_per_m / 2.0
    c1, c2 = _random_colours(rng, 2, hue, HUE_SPREAD).astype(np.float32)
    mix = 0.5 + 0.5 * _value_noise(rng, h2, w2, BASE_MIX_WAVELENGTH_M * tpm2)
    grain = np.zeros((h2, w2), dtype=np.float32)
    for wavelength_m, amplitude in NOISE_OCTAVES_M:
        grain += amplitude * _value_noise(rng, h2, w2, wavelength_m * tpm2)
    img = c1[None, None, :] + mix[..., None] * (c2 - c1)[None, None, :] + grain[..., None]
    small = np.clip(img, 0, 255).astype(np.uint8)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)


def _rotated_rect(cx: float, cy: float, w: float, h: float, angle: float) -> NDArray[np.int32]:
    c, s = math.cos(angle), math.sin(angle)
    corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]], dtype=np.float64) / 2.0
    pts = corners @ np.array([[c, s], [-s, c]]) + (cx, cy)
    return np.round(pts).astype(np.int32)


@dataclass(frozen=True)
class _ShapeDraws:
    """Random parameters of n shapes, drawn in one go (per-shape generator calls dominate the cost)."""

    xy: NDArray[np.float64]  # (n, 2) centre, texels (may lie a little outside the texture)
    kind: NDArray[np.int64]  # (n,) which of the 9 shape kinds
    angle: NDArray[np.float64]  # (n,) orientation, rad
    aspect: NDArray[np.float64]  # (n,) in [0.3, 1): minor/major ratio
    count: NDArray[np.int64]  # (n,) in [2, 5): vertices, cells, bars or glyphs
    colour: NDArray[np.int64]  # (n, 3) BGR
    colour2: NDArray[np.int64]  # (n, 3) BGR, second colour of checkers
    jitter: NDArray[np.float64]  # (n, 5, 2) per-vertex angle (rad, sorted) and radius factor of polygons
    glyphs: NDArray[np.int64]  # (n, 4) indices into _GLYPHS


def _shape_draws(
    rng: np.random.Generator, n: int, sizes_px: NDArray[np.float64], h: int, w: int, hue: float
) -> _ShapeDraws:
    pad = sizes_px / 2
    xy = np.stack([rng.uniform(-pad, w + pad), rng.uniform(-pad, h + pad)], axis=1)
    jitter = np.stack([np.sort(rng.uniform(0, 2 * math.pi, (n, 5)), axis=1), rng.uniform(0.5, 1.0, (n, 5))], axis=2)
    return _ShapeDraws(
        xy=xy,
        kind=rng.integers(0, 9, n),
        angle=rng.uniform(0, math.pi, n),
        aspect=rng.uniform(0.3, 1.0, n),
        count=rng.integers(2, 5, n),
        # Mostly the texture's own hue family; a few shapes of any hue.
        colour=np.where(
            rng.random((n, 1)) < 0.85, _random_colours(rng, n, hue, HUE_SPREAD), _random_colours(rng, n, 0, 90)
        ),
        colour2=_random_colours(rng, n, hue, HUE_SPREAD),
        jitter=jitter,
        glyphs=rng.integers(0, len(_GLYPHS), (n, 4)),
    )


def _draw_shape(img: U8, d: _ShapeDraws, i: int, size_px: float) -> None:
    """Draw shape ``i`` of ``d`` with size ``size_px`` texels into ``img`` (in place)."""
    cx, cy = float(d.xy[i, 0]), float(d.xy[i, 1])
    centre = (round(cx), round(cy))
    colour = tuple(int(c) for c in d.colour[i])
    kind, angle, aspect, count = int(d.kind[i]), float(d.angle[i]), float(d.aspect[i]), int(d.count[i])
    r = max(size_px / 2.0, 1.0)
    if kind == 0:  # filled disc
        cv2.circle(img, centre, round(r), colour, -1, cv2.LINE_AA)
    elif kind == 1:  # ring
        cv2.circle(img, centre, round(r), colour, max(1, round(r / 4)), cv2.LINE_AA)
    elif kind == 2:  # filled ellipse
        axes = (round(r), max(1, round(r * aspect)))
        cv2.ellipse(img, centre, axes, math.degrees(angle), 0, 360, colour, -1, cv2.LINE_AA)
    elif kind == 3:  # rotated rectangle
        cv2.fillConvexPoly(img, _rotated_rect(cx, cy, size_px, size_px * aspect, angle), colour, cv2.LINE_AA)
    elif kind == 4:  # triangle / irregular polygon
        a, rad = d.jitter[i, : count + 1, 0], r * d.jitter[i, : count + 1, 1]
        pts = np.stack([cx + rad * np.cos(a), cy + rad * np.sin(a)], axis=1)
        cv2.fillPoly(img, [np.round(pts).astype(np.int32)], colour, cv2.LINE_AA)
    elif kind == 5:  # bar
        dx, dy = r * math.cos(angle), r * math.sin(angle)
        p0, p1 = (round(cx - dx), round(cy - dy)), (round(cx + dx), round(cy + dy))
        cv2.line(img, p0, p1, colour, max(1, round(r * aspect * 0.35)), cv2.LINE_AA)
    elif kind == 6:  # 1-3 glyphs
        text = "".join(_GLYPHS[g] for g in d.glyphs[i, : count - 1])
        scale = size_px / 22.0  # Hershey simplex glyphs are ~22 px tall at scale 1
        org = (round(cx - r), round(cy + r))
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, max(1, round(scale * 2.5)))
    elif kind == 7:  # small checker patch (a local, short repetition only)
        cell = size_px / count
        other = tuple(int(c) for c in d.colour2[i])
        for a_ in range(count):
            for b_ in range(count):
                x0, y0 = cx - size_px / 2 + a_ * cell, cy - size_px / 2 + b_ * cell
                col = colour if (a_ + b_) % 2 == 0 else other
                cv2.rectangle(img, (round(x0), round(y0)), (round(x0 + cell), round(y0 + cell)), col, -1)
    else:  # stripe patch: a few parallel bars
        dx, dy = math.cos(angle), math.sin(angle)
        thick = max(1, round(size_px / (3 * count)))
        for k in range(count):
            off = (k - (count - 1) / 2) * size_px / count
            ox, oy = cx - dy * off, cy + dx * off
            p0 = (round(ox - dx * r), round(oy - dy * r))
            p1 = (round(ox + dx * r), round(oy + dy * r))
            cv2.line(img, p0, p1, colour, thick, cv2.LINE_AA)


def generate_texture(seed: int, key: str, width_px: int, height_px: int, texels_per_m: float) -> U8:
    """Render texture ``key`` of world ``seed``.

    width_px, height_px: texture size in texels; texels_per_m: texel density, used so that shapes and
    noise have fixed physical sizes. Returns (height_px, width_px, 3) uint8 BGR.
    """
    rng = texture_rng(seed, key)
    hue = float(rng.uniform(0, 180))  # each texture has its own colour family (OpenCV hue units)
    img = _base_layer(rng, height_px, width_px, texels_per_m, hue)
    area_m2 = width_px * height_px / texels_per_m**2
    n_shapes = int(rng.poisson(SHAPES_PER_M2 * area_m2))
    lo, hi = SHAPE_SIZE_RANGE_M
    # Big shapes first so small detail lands on top of them rather than being painted over.
    sizes_px = np.sort(np.exp(rng.uniform(math.log(lo), math.log(hi), n_shapes)))[::-1] * texels_per_m
    draws = _shape_draws(rng, n_shapes, sizes_px, height_px, width_px, hue)
    for i in range(n_shapes):
        _draw_shape(img, draws, i, float(sizes_px[i]))
    return img


def build_mipmaps(image: U8, n_levels: int) -> list[U8]:
    """Mip pyramid: level 0 is ``image``, level l is 2^l times smaller (box filter, cv2.INTER_AREA).

    image: (H, W) or (H, W, 3) uint8 with H and W divisible by 2^(n_levels-1), so each texel of level l
    covers exactly 2^l x 2^l texels of level 0 (keeps the texture-to-plane mapping exact at every level).
    """
    levels = [image]
    for _ in range(1, n_levels):
        prev = levels[-1]
        h, w = prev.shape[:2]
        if h < 2 or w < 2:
            break
        levels.append(np.asarray(cv2.resize(prev, (w // 2, h // 2), interpolation=cv2.INTER_AREA), dtype=np.uint8))
    return levels


@dataclass
class TextureBank:
    """Lazily generated, cached textures and mip pyramids of one world seed.

    ``get(key, width_px, height_px, texels_per_m, colour)`` returns the mip pyramid (a list, level 0 first) of
    the grey (H, W) or colour (H, W, 3) texture. A texture is generated once, on first use, and the grey and
    colour pyramids are derived from the same BGR pixels.
    """

    seed: int
    n_levels: int
    _bgr: dict[tuple[str, int, int], U8] = field(default_factory=dict)
    _pyramids: dict[tuple[str, int, int, bool], list[U8]] = field(default_factory=dict)

    def get(self, key: str, width_px: int, height_px: int, texels_per_m: float, colour: bool) -> list[U8]:
        pkey = (key, width_px, height_px, colour)
        pyramid = self._pyramids.get(pkey)
        if pyramid is None:
            bkey = (key, width_px, height_px)
            bgr = self._bgr.get(bkey)
            if bgr is None:
                bgr = generate_texture(self.seed, key, width_px, height_px, texels_per_m)
                self._bgr[bkey] = bgr
            base = bgr if colour else np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
            pyramid = build_mipmaps(base, self.n_levels)
            self._pyramids[pkey] = pyramid
        return pyramid
