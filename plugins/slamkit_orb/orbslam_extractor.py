"""ORB-SLAM's own ORB extractor (Mur-Artal et al., T-RO 2015, sec. III-A; ``ORBextractor.cc``).

Per frame: an 8-level pyramid with scale factor 1.2; on every level FAST corners from a grid of ~30 px
cells with a fallback threshold for weak cells (grid_fast.py); a quadtree spreads the level's corners over
the image and keeps the level's share of the feature budget (quadtree.py, pyramid.py); orientation by
intensity centroid (orientation.py); 256-bit steered BRIEF descriptors on the Gaussian-blurred level image.

Descriptors come from ``cv2.ORB.compute`` on our keypoints. With provided keypoints OpenCV (orb.cpp,
``detectAndCompute`` with ``useProvidedKeypoints``) builds the same pyramid as pyramid.py (INTER_LINEAR_EXACT
from level to level, float32 sizes, each level with a BORDER_REFLECT_101 border of its own), blurs each level
with a 7x7 Gaussian of sigma 2 (BORDER_REFLECT_101), and samples its learned 256-pair pattern
(``bit_pattern_31_``, the one ORB-SLAM uses) rotated by the keypoint's ``angle`` around round(pt / scale_factor **
octave) on level ``octave``: exactly ORB-SLAM's ``computeDescriptors``. So each level's keypoints go to one
``compute`` call on our level image (``nlevels=1``, octave 0), which gives the same bits without OpenCV building
its own pyramid; tests/unit/orb/test_descriptors.py checks that the bits are OpenCV's multi-level computation
on the full image and that they are invariant to a 90 deg rotation.

The levels are independent: with the compiled FAST backend they are dealt out to ``n_threads`` groups of about
equal area, one compiled call and one descriptor call per level per group (the calling thread takes one group,
pool threads the others); with the opencv backend each level is a task of its own. The output is assembled in
level order and does not depend on the thread count.

The GIL: each call into OpenCV or a compiled kernel releases it and takes it back, and taking it back waits up
to a switch interval whenever another thread is running Python (local mapping, in the threaded runner). With
one such release per keypoint (a ``cv2.KeyPoint`` constructor), per level and per numpy step, extraction took
39 ms instead of 5 beside a thread running Python; with the compiled level kernel (level_kernel.py) and one
descriptor call per image, 11 ms (``python benchmarks/extraction_gil.py``).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError
from slamkit.features import Features
from slamkit.interfaces import Camera
from slamkit.thread_budget import is_single_threaded
from slamkit_orb.grid_fast import FAST_BACKENDS, FAST_RADIUS, FastBackend, GridFast
from slamkit_orb.level_kernel import levels_keypoints
from slamkit_orb.orientation import circular_patch_extent, intensity_centroid_angles
from slamkit_orb.pyramid import (
    PackedPyramid,
    build_packed_pyramid,
    build_pyramid,
    features_per_level,
    level_scales,
    level_sizes,
)
from slamkit_orb.quadtree import distribute_quadtree

#: ORB's learned test pattern is defined on a 31 x 31 patch (OpenCV falls back to a random one otherwise).
_PATTERN_PATCH_SIZE = 31
_DESCRIPTOR_BYTES = 32


@dataclass(frozen=True)
class LevelKeypoints:
    """Keypoints of one image in their own level's pixels.

    xy: (N, 2) int32 column/row in the level image; level: (N,) int32; response: (N,) float32 FAST score;
    angle_deg: (N,) float32 in [0, 360); descriptors: (N, 32) uint8.
    """

    xy: NDArray[np.int32]
    level: NDArray[np.int32]
    response: NDArray[np.float32]
    angle_deg: NDArray[np.float32]
    descriptors: NDArray[np.uint8]


def _surviving_rows(xy: NDArray[np.int32], out_keypoints: Sequence[cv2.KeyPoint]) -> NDArray[np.int64]:
    """Rows of ``xy`` (n, 2) integer level positions that OpenCV's ``compute`` kept, in its output order (the
    keypoints it returned, each at its input position: a level's corners are distinct pixels)."""
    out_xy = np.rint(np.asarray(cv2.KeyPoint.convert(list(out_keypoints)), np.float64).reshape(-1, 2)).astype(np.int64)
    width = int(max(int(xy[:, 0].max(initial=0)), int(out_xy[:, 0].max(initial=0)))) + 1
    key = xy[:, 1].astype(np.int64) * width + xy[:, 0]
    order = np.argsort(key)
    pos = np.searchsorted(key[order], out_xy[:, 1] * width + out_xy[:, 0])
    return order[pos].astype(np.int64)


@dataclass(frozen=True)
class _LevelResult:
    """One level's oriented keypoints with their descriptors (the keypoints OpenCV gave none are left out)."""

    level: int
    xy: NDArray[np.int32]
    response: NDArray[np.float32]
    angle_deg: NDArray[np.float32]
    descriptors: NDArray[np.uint8]


def _int_param(value: object, key: str, low: int, high: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ConfigError(f"features.{key} must be an integer, got {value!r}")
    if value < low or (high is not None and value > high):
        bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise ConfigError(f"features.{key} must be {bound}, got {value}")
    return int(value)


class OrbSlamExtractor:
    """ORB-SLAM's ORB extractor behind slamkit's FeatureExtractor interface.

    n_features: feature budget per image (ORB-SLAM: 1000 at 640x480, 2000 for KITTI).
    scale_factor, n_levels: the pyramid (1.2, 8).
    ini_fast_threshold, min_fast_threshold: FAST thresholds, grey levels; the lower one is used in grid cells
        where the higher finds nothing (20, 7).
    cell_size_px: nominal grid cell side, px (30).
    edge_threshold: px, no keypoint closer than this to a level's border (19).
    patch_size, half_patch_size: the descriptor patch (31) and the orientation patch radius (15).
    n_threads: worker threads the pyramid levels are shared among (1: all in the caller's thread; so is every
        extraction a caller runs inside slamkit.thread_budget.single_threaded). The output does not depend on it.
    fast_backend: FAST implementation: "compiled" (fast9.py, numba; faster and holds no GIL) or "opencv"
        (cv2.FastFeatureDetector). The output does not depend on it.

    Output keypoints are in level-0 pixels (level coordinates times scale_factor ** level); ``level`` is the
    pyramid level (octave). An image too small for a level simply yields no keypoints there; a blank image
    yields none at all.
    """

    def __init__(
        self,
        n_features: int = 1000,
        scale_factor: float = 1.2,
        n_levels: int = 8,
        ini_fast_threshold: int = 20,
        min_fast_threshold: int = 7,
        cell_size_px: int = 30,
        edge_threshold: int = 19,
        patch_size: int = 31,
        half_patch_size: int = 15,
        n_threads: int = 2,
        fast_backend: FastBackend = "compiled",
    ) -> None:
        self.n_features = _int_param(n_features, "n_features", 1)
        if isinstance(scale_factor, bool) or not isinstance(scale_factor, int | float) or not scale_factor > 1.0:
            raise ConfigError(f"features.scale_factor must be a number > 1, got {scale_factor!r}")
        self.scale_factor = float(scale_factor)
        self.n_levels = _int_param(n_levels, "n_levels", 1, 32)
        self.ini_fast_threshold = _int_param(ini_fast_threshold, "ini_fast_threshold", 1, 254)
        self.min_fast_threshold = _int_param(min_fast_threshold, "min_fast_threshold", 1, self.ini_fast_threshold)
        self.cell_size_px = _int_param(cell_size_px, "cell_size_px", 2 * FAST_RADIUS + 1)
        self.patch_size = _int_param(patch_size, "patch_size", _PATTERN_PATCH_SIZE, _PATTERN_PATCH_SIZE)
        self.half_patch_size = _int_param(half_patch_size, "half_patch_size", 1, self.patch_size // 2)
        # The orientation patch must fit inside the level image around every keypoint.
        self.edge_threshold = _int_param(edge_threshold, "edge_threshold", max(self.half_patch_size, FAST_RADIUS))
        self.n_threads = _int_param(n_threads, "n_threads", 1, 64)
        if fast_backend not in FAST_BACKENDS:
            raise ConfigError(f"features.fast_backend must be one of {', '.join(FAST_BACKENDS)}, got {fast_backend!r}")
        self.fast_backend: FastBackend = fast_backend
        self._pool: ThreadPoolExecutor | None = None

        self.level_budget = features_per_level(self.n_features, self.scale_factor, self.n_levels)
        self.level_scale = level_scales(self.scale_factor, self.n_levels)
        self._u_max = circular_patch_extent(self.half_patch_size)
        self._grid = GridFast(
            self.edge_threshold,
            self.cell_size_px,
            self.ini_fast_threshold,
            self.min_fast_threshold,
            self.fast_backend,
        )
        self._local = threading.local()  # one cv2.ORB per worker thread
        self._weak_hint = np.ones(self.n_levels)  # per level: share of weak grid cells in the last frame

    def __del__(self) -> None:
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)

    def _descriptor(self) -> cv2.ORB:
        """This thread's cv2.ORB for one level image (``nlevels=1``), used only for ORB.compute on our keypoints
        (nfeatures, the scale factor, the score type and the FAST threshold play no part there)."""
        orb: cv2.ORB | None = getattr(self._local, "orb", None)
        if orb is None:
            orb = cv2.ORB.create(
                nfeatures=self.n_features,
                nlevels=1,
                edgeThreshold=self.edge_threshold,
                firstLevel=0,
                WTA_K=2,
                patchSize=self.patch_size,
            )
            self._local.orb = orb
        return orb

    def __repr__(self) -> str:
        return (
            f"OrbSlamExtractor(n_features={self.n_features}, scale_factor={self.scale_factor}, "
            f"n_levels={self.n_levels}, ini_fast_threshold={self.ini_fast_threshold}, "
            f"min_fast_threshold={self.min_fast_threshold}, cell_size_px={self.cell_size_px}, "
            f"edge_threshold={self.edge_threshold}, patch_size={self.patch_size}, "
            f"half_patch_size={self.half_patch_size}, n_threads={self.n_threads}, "
            f"fast_backend={self.fast_backend!r})"
        )

    @staticmethod
    def _check_image(image: object) -> NDArray[np.uint8]:
        if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
            got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"extract: image must be an (H, W) uint8 grey array, got {got}")
        return np.ascontiguousarray(image)

    def _level(self, level: int, level_image: NDArray[np.uint8]) -> _LevelResult | None:
        """Corners, quadtree selection and orientation of one level with the opencv FAST backend, step by step
        (runs in a worker thread: OpenCV and the numba kernels release the GIL). The compiled backend does the
        same in level_kernel.py (_compiled_levels)."""
        # FAST strategy from the share of weak cells this level had last frame (any strategy gives the same
        # corners; this only picks the faster, see grid_fast.py).
        corners = self._grid.detect(level_image, "auto", float(self._weak_hint[level]))
        self._weak_hint[level] = corners.weak_share
        if corners.response.size == 0:
            return None
        x0, y0, x1, y1 = corners.region
        keep = distribute_quadtree(
            (corners.xy[:, 0] - x0).astype(np.float64),
            (corners.xy[:, 1] - y0).astype(np.float64),
            corners.response,
            x1 - x0,
            y1 - y0,
            int(self.level_budget[level]),
        )
        xy = np.ascontiguousarray(corners.xy[keep])
        return self._described(
            level, level_image, xy, corners.response[keep], intensity_centroid_angles(level_image, xy, self._u_max)
        )

    def _described(
        self,
        level: int,
        level_image: NDArray[np.uint8],
        xy: NDArray[np.int32],
        response: NDArray[np.float32],
        angle: NDArray[np.float32],
    ) -> _LevelResult:
        """One level's keypoints with their (n, 32) uint8 rBRIEF descriptors, those OpenCV gave none left out.

        One ``ORB.compute`` on the level image (``nlevels=1``, the keypoints at their level position, octave 0):
        OpenCV adds the same BORDER_REFLECT_101 border to it as to the level of its own pyramid, blurs it (7x7,
        sigma 2) and samples the rotated pattern around the keypoint, so the bits are those of one ``compute`` on
        the full image with each keypoint at octave = its level (tests/unit/orb/test_descriptors.py), without
        OpenCV building a second pyramid, and each level group's thread describes its own levels. The KeyPoints
        of a level come from one binding call and get their angle and index as attributes: every cv2 call (a
        KeyPoint constructor too) releases and re-takes the GIL, which costs up to a switch interval each while
        another thread runs Python. Keypoints lie >= edge_threshold px inside their level, so OpenCV's border
        filter keeps them all and the descriptors come in the keypoints' order; should it drop some, the survivors are
        found by position (``_surviving_rows``; a level's FAST corners are distinct pixels).
        """
        keypoints = cv2.KeyPoint.convert(xy.astype(np.float32), float(self.patch_size), 0.0, 0, 0)  # type: ignore[call-overload]  # stubs: no ndarray
        for keypoint, a in zip(keypoints, angle.tolist(), strict=True):
            keypoint.angle = a
        out_keypoints, descriptors = self._descriptor().compute(level_image, keypoints)
        if descriptors is None or len(out_keypoints) == 0:
            has = np.zeros(0, np.int64)
            return _LevelResult(level, xy[has], response[has], angle[has], np.zeros((0, _DESCRIPTOR_BYTES), np.uint8))
        bits: NDArray[np.uint8] = np.asarray(descriptors, np.uint8)
        if len(out_keypoints) == len(keypoints):  # OpenCV only filters the keypoints (border, level), never reorders
            return _LevelResult(level, xy, response, angle, bits)
        rows = _surviving_rows(xy, out_keypoints)
        order = np.argsort(rows, kind="stable")  # the input's order, as when nothing is dropped
        has = rows[order]
        return _LevelResult(level, xy[has], response[has], angle[has], bits[order])

    def _level_group(self, levels: list[int], pyramid: list[NDArray[np.uint8]]) -> list[_LevelResult | None]:
        """The keypoints of some levels in one compiled call (level_kernel.levels_keypoints)."""
        xy, response, angle, counts, weak = levels_keypoints(
            self._grid, [pyramid[k] for k in levels], [int(self.level_budget[k]) for k in levels], self._u_max
        )
        out: list[_LevelResult | None] = []
        start = 0
        for level, count, weak_share in zip(levels, counts.tolist(), weak.tolist(), strict=True):
            self._weak_hint[level] = weak_share
            part = slice(start, start + count)
            out.append(self._described(level, pyramid[level], xy[part], response[part], angle[part]) if count else None)
            start += count
        return out

    def _compiled_levels(
        self, pyramid: list[NDArray[np.uint8]], pool: ThreadPoolExecutor | None
    ) -> list[_LevelResult | None]:
        """Every level's keypoints, in level order, with one compiled call per thread: the levels are dealt out
        to ``n_threads`` groups of about equal area (the calling thread works on the first)."""
        n_groups = 1 if pool is None else min(self.n_threads, len(pyramid))
        groups: list[list[int]] = [[] for _ in range(n_groups)]
        area = [0] * n_groups
        for level in sorted(range(len(pyramid)), key=lambda k: -pyramid[k].size):  # largest first, to the least loaded
            g = area.index(min(area))
            groups[g].append(level)
            area[g] += pyramid[level].size
        groups = [sorted(g) for g in groups if g]
        futures = [pool.submit(self._level_group, g, pyramid) for g in groups[1:]] if pool is not None else []
        by_level: dict[int, _LevelResult | None] = dict(
            zip(groups[0], self._level_group(groups[0], pyramid), strict=True)
        )
        for group, future in zip(groups[1:], futures, strict=True):
            by_level.update(zip(group, future.result(), strict=True))
        return [by_level[level] for level in range(len(pyramid))]

    def _executor(self) -> ThreadPoolExecutor | None:
        """The level threads' pool; None (all levels in the calling thread) with one thread, or while the caller
        asked for its work to stay in its thread (slamkit.thread_budget: extraction beside a busy thread)."""
        if self.n_threads < 2 or is_single_threaded():
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.n_threads, thread_name_prefix="orb-level")
        return self._pool

    def detect_and_describe(self, image: NDArray[np.uint8]) -> LevelKeypoints:
        """image: (H, W) uint8 grey -> keypoints with orientation and descriptors, by level, in level pixels."""
        image = self._check_image(image)
        h, w = image.shape
        pyramid = build_pyramid(image, level_sizes(w, h, self.scale_factor, self.n_levels))
        return self._keypoints(pyramid, self._executor())

    def _keypoints(self, pyramid: list[NDArray[np.uint8]], pool: ThreadPoolExecutor | None) -> LevelKeypoints:
        """The keypoints of the level images ``pyramid`` (level 0 first), the levels shared out to ``pool``'s
        threads (None: all in the calling thread)."""
        if self.fast_backend == "compiled":
            results = self._compiled_levels(pyramid, pool)
        elif pool is None:
            results = [self._level(level, img) for level, img in enumerate(pyramid)]
        else:
            futures = [pool.submit(self._level, level, img) for level, img in enumerate(pyramid)]
            results = [f.result() for f in futures]
        found = [r for r in results if r is not None and r.xy.shape[0] > 0]
        if not found:
            return LevelKeypoints(
                np.zeros((0, 2), np.int32),
                np.zeros(0, np.int32),
                np.zeros(0, np.float32),
                np.zeros(0, np.float32),
                np.zeros((0, _DESCRIPTOR_BYTES), np.uint8),
            )
        return LevelKeypoints(
            np.concatenate([r.xy for r in found]),
            np.concatenate([np.full(r.xy.shape[0], r.level, dtype=np.int32) for r in found]),
            np.concatenate([r.response for r in found]),
            np.concatenate([r.angle_deg for r in found]),
            np.concatenate([r.descriptors for r in found]),
        )

    def extract(self, image: NDArray[np.uint8], camera: Camera | None = None) -> Features:
        """image: (H, W) uint8 grey -> Features.

        uv_px are level-0 px of the raw image. With a camera, uv_undist_px = camera.undistort_points(uv_px);
        keypoints the camera model cannot undistort (beyond its valid radius: NaN) are dropped. Raises
        CalibrationError when the camera's size differs from the image's.
        """
        image = self._checked(image, camera)
        return self._features(self.detect_and_describe(image), camera)

    def extract_with_pyramid(
        self, image: NDArray[np.uint8], camera: Camera | None = None, threaded: bool = True
    ) -> tuple[Features, PackedPyramid]:
        """:meth:`extract`, and the pyramid the keypoints were found on (ORB-SLAM's ``mvImagePyramid``: the stereo
        front end's SAD windows are read from it, as in ORB-SLAM2's ComputeStereoMatches), packed into one array.

        threaded: share the levels out to ``n_threads`` threads as :meth:`extract` does; False: all in the calling
        thread (a caller running two extractions at once, one per thread, keeps the machine's cores busy without
        a third and fourth thread). The features are those of :meth:`extract` either way."""
        image = self._checked(image, camera)
        h, w = image.shape
        pyramid = build_packed_pyramid(image, level_sizes(w, h, self.scale_factor, self.n_levels))
        kps = self._keypoints(pyramid.levels, self._executor() if threaded else None)
        return self._features(kps, camera), pyramid

    def _checked(self, image: object, camera: Camera | None) -> NDArray[np.uint8]:
        """The image as a contiguous (H, W) uint8 array; CalibrationError when the camera's size differs."""
        checked = self._check_image(image)
        h, w = checked.shape
        if camera is not None and (int(camera.width), int(camera.height)) != (w, h):
            raise CalibrationError(
                f"extract: image is {w}x{h} px but the camera ({camera.model}) is calibrated for "
                f"{camera.width}x{camera.height} px"
            )
        return checked

    def _features(self, kps: LevelKeypoints, camera: Camera | None) -> Features:
        """Level keypoints -> Features in level-0 px, undistorted through the camera when one is given."""
        uv = kps.xy.astype(np.float32) * self.level_scale[kps.level][:, None]
        if camera is not None and uv.shape[0]:
            uv_undist = np.asarray(camera.undistort_points(uv.astype(np.float64)), dtype=np.float64)
            ok = np.all(np.isfinite(uv_undist), axis=1)
            if not np.all(ok):
                uv, uv_undist, kps = uv[ok], uv_undist[ok], _take(kps, np.flatnonzero(ok))
            uv_undist_f32 = uv_undist.astype(np.float32)
        else:
            uv_undist_f32 = uv.copy()
        return Features(
            uv_px=uv,
            uv_undist_px=uv_undist_f32,
            level=kps.level,
            angle_deg=kps.angle_deg,
            response=kps.response,
            descriptors=kps.descriptors,
            scale_factor=self.scale_factor,
            n_levels=self.n_levels,
        )


def _take(kps: LevelKeypoints, index: NDArray[np.int64]) -> LevelKeypoints:
    return LevelKeypoints(
        kps.xy[index], kps.level[index], kps.response[index], kps.angle_deg[index], kps.descriptors[index]
    )
