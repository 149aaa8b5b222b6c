"""The rectified stereo front end (``frontend=stereo``): ORB in both images (the two extractions in parallel: the
extractor's kernels release the GIL) and ORB-SLAM2's stereo matching (Mur-Artal & Tardos 2017, sec. III-A;
Frame::ComputeStereoMatches), in one numba kernel:

1. every right keypoint is listed on the image rows within 2 x its level's scale of its own row;
2. each left keypoint takes, of the right keypoints listed on its row, at a level within one of its own and with
   u_right in [u_left - fx, u_left] (depth above one baseline), the one of least Hamming distance; it needs a
   distance below (TH_HIGH + TH_LOW) / 2 = 75;
3. the match is refined on the keypoint's pyramid level: an 11 x 11 window of the left image (minus its centre
   value) slid along the row of the right image over +-5 px around the match by sum of absolute differences; a best
   offset at either end of the slide is rejected, else a parabola through the three SADs around the best gives the
   sub-pixel offset (rejected beyond +-1 px), scaled back to level 0;
4. a disparity in [0, fx) gives depth bf / disparity (a zero disparity becomes 0.01 px);
5. matches whose SAD is at least 1.5 x 1.4 x the median SAD are dropped (outliers).

Keypoints are those of the rectified images as the dataset gives them (``uv_px``, no undistortion), and the record's
``u_right_px`` / ``depth_m`` are NaN for unmatched keypoints. bf is baseline x fx of the rectified pair, from the
dataset (``T_l_r``) when the front end is bound to it (``bind_dataset``), else the config's ``bf``.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import Any, ClassVar

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError, DatasetError
from slamkit.features import Features, Observations
from slamkit.frontend.mono import MonocularFrontEnd
from slamkit.interfaces import Camera, FeatureExtractor
from slamkit.sensors import FrameData

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@numba.njit(cache=True, nogil=True, inline="always")
def _hamming(a: NDArray[np.uint8], b: NDArray[np.uint8], table: NDArray[np.int64]) -> int:  # pragma: no cover
    d = 0
    for k in range(a.shape[0]):
        d += table[a[k] ^ b[k]]
    return d


@numba.njit(cache=True, nogil=True, inline="always")
def _sad_slide(
    pyr_l: NDArray[np.uint8],
    pyr_r: NDArray[np.uint8],
    off: int,
    width: int,
    vl: int,
    ul: int,
    ur0: int,
    w: int,
    slide: int,
    dists: NDArray[np.int32],
) -> None:  # pragma: no cover - numba
    """dists[k] (k = 0 .. 2 slide) = sum of |(IL - IL[centre]) - (IR - IR[centre])| over the (2w+1)^2 windows centred
    at (ul, vl) of the left level image and (ur0 - slide + k, vl) of the right one (both stored row-major from
    ``off`` with ``width`` columns; the caller keeps every window inside the level).

    Integer sums (at most 121 x 510 for w = 5: int32 holds them), the same values as ORB-SLAM's float sums of
    integers. Indices are uint64 (numba checks a signed index for wraparound at every access, an unsigned one it
    does not) and the window's rows are the inner loops, which LLVM vectorizes."""
    side = 2 * w + 1
    lc = np.int32(pyr_l[np.uint64(off + vl * width + ul)])
    for k in range(2 * slide + 1):
        ur = ur0 - slide + k
        c = lc - np.int32(pyr_r[np.uint64(off + vl * width + ur)])
        s = np.int32(0)
        for dy in range(side):
            row_l = np.uint64(off + (vl - w + dy) * width + ul - w)
            row_r = np.uint64(off + (vl - w + dy) * width + ur - w)
            for dx in range(side):
                s += abs(np.int32(pyr_l[row_l + np.uint64(dx)]) - np.int32(pyr_r[row_r + np.uint64(dx)]) - c)
        dists[k] = s


@numba.njit(cache=True, nogil=True)
def _stereo_match_kernel(
    uv_l: F32,
    lev_l: I64,
    desc_l: NDArray[np.uint8],
    uv_r: F32,
    lev_r: I64,
    desc_r: NDArray[np.uint8],
    scales: F64,
    pyr_l: NDArray[np.uint8],
    pyr_r: NDArray[np.uint8],
    offsets: I64,
    widths: I64,
    heights: I64,
    bf: float,
    min_d: float,
    max_d: float,
    th_orb: int,
    band: float,
    w: int,
    slide: int,
    table: NDArray[np.int64],
    start: int,
    step: int,
) -> tuple[F32, F32, F32]:  # pragma: no cover - numba
    """-> (u_right (N,), depth (N,), sad (N,)), NaN where unmatched (see the module docstring, steps 1-4), of the left
    keypoints start, start + step, ... (the others NaN): the front end matches the even and the odd ones in two
    threads."""
    n_l = uv_l.shape[0]
    n_r = uv_r.shape[0]
    rows = heights[0]
    u_right = np.full(n_l, np.nan, np.float32)
    depth = np.full(n_l, np.nan, np.float32)
    sad = np.full(n_l, np.nan, np.float32)
    # step 1: row table (CSR)
    count = np.zeros(rows + 1, np.int64)
    for i in range(n_r):
        r = band * scales[lev_r[i]]
        lo = max(int(np.floor(uv_r[i, 1] - r)), 0)
        hi = min(int(np.ceil(uv_r[i, 1] + r)), rows - 1)
        for y in range(lo, hi + 1):
            count[y + 1] += 1
    for y in range(rows):
        count[y + 1] += count[y]
    fill = count[:-1].copy()
    table_r = np.empty(count[rows], np.int64)
    for i in range(n_r):
        r = band * scales[lev_r[i]]
        lo = max(int(np.floor(uv_r[i, 1] - r)), 0)
        hi = min(int(np.ceil(uv_r[i, 1] + r)), rows - 1)
        for y in range(lo, hi + 1):
            table_r[fill[y]] = i
            fill[y] += 1
    dists = np.empty(2 * slide + 1, np.int32)
    for i in range(start, n_l, step):
        ul = uv_l[i, 0]
        vl = uv_l[i, 1]
        row = int(vl)
        if row < 0 or row >= rows:
            continue
        min_u = ul - max_d
        max_u = ul - min_d
        if max_u < 0:
            continue
        level = lev_l[i]
        best = th_orb + 1000
        best_r = -1
        # step 2: descriptor search along the row band, in the disparity range
        for k in range(count[row], count[row + 1]):
            j = table_r[k]
            if lev_r[j] < level - 1 or lev_r[j] > level + 1:
                continue
            ur = uv_r[j, 0]
            if ur >= min_u and ur <= max_u:
                d = _hamming(desc_l[i], desc_r[j], table)
                if d < best:
                    best = d
                    best_r = j
        if best_r < 0 or best >= th_orb:
            continue
        # step 3: SAD window on the keypoint's level, parabola fit
        inv = 1.0 / scales[level]
        sul = int(np.round(ul * inv))
        svl = int(np.round(vl * inv))
        sur0 = int(np.round(uv_r[best_r, 0] * inv))
        width = widths[level]
        height = heights[level]
        off = offsets[level]
        if svl - w < 0 or svl + w >= height or sul - w < 0 or sul + w >= width:
            continue
        if sur0 - slide - w < 0 or sur0 + slide + w >= width:
            continue
        _sad_slide(pyr_l, pyr_r, off, width, svl, sul, sur0, w, slide, dists)
        best_sad = np.inf
        best_inc = 0
        for inc in range(-slide, slide + 1):
            s = float(dists[slide + inc])
            if s < best_sad:
                best_sad = s
                best_inc = inc
        if best_inc == -slide or best_inc == slide:
            continue
        d1 = float(dists[slide + best_inc - 1])
        d2 = float(dists[slide + best_inc])
        d3 = float(dists[slide + best_inc + 1])
        den = 2.0 * (d1 + d3 - 2.0 * d2)
        if den == 0.0:
            continue
        delta = (d1 - d3) / den
        if delta < -1.0 or delta > 1.0:
            continue
        best_ur = scales[level] * (sur0 + best_inc + delta)
        disparity = ul - best_ur
        # step 4
        if disparity >= min_d and disparity < max_d:
            if disparity <= 0.0:
                disparity = 0.01
                best_ur = ul - 0.01
            depth[i] = bf / disparity
            u_right[i] = best_ur
            sad[i] = best_sad
    return u_right, depth, sad


def _popcount_table() -> NDArray[np.int64]:
    return np.array([bin(i).count("1") for i in range(256)], np.int64)


_POPCOUNT = _popcount_table()


#: an image pyramid packed into one array: (pixels (sum of w x h,) uint8, offsets, widths, heights (n_levels,) int64);
#: level l is pixels[offsets[l] : offsets[l] + widths[l] * heights[l]], row-major
Pyramid = tuple[NDArray[np.uint8], I64, I64, I64]


def image_pyramid(image: NDArray[np.uint8], n_levels: int, scale_factor: float) -> Pyramid:
    """ORB-SLAM's image pyramid (ORBextractor::ComputePyramid: level l is level l-1 resized by INTER_LINEAR to
    round(size / scale_factor^l)) packed row-major into one uint8 array -> (pixels, offsets, widths, heights).

    Each level is resized straight into its place in the packed array (no per-level copy)."""
    h, w = image.shape[:2]
    sizes_wh = [(w, h)]
    for lev in range(1, n_levels):
        s = scale_factor**lev
        sizes_wh.append((round(w / s), round(h / s)))
    widths = np.array([sw for sw, _ in sizes_wh], np.int64)
    heights = np.array([sh for _, sh in sizes_wh], np.int64)
    sizes = widths * heights
    offsets = np.zeros(n_levels, np.int64)
    offsets[1:] = np.cumsum(sizes)[:-1]
    pixels = np.empty(int(sizes.sum()), np.uint8)
    previous = pixels[: w * h].reshape(h, w)
    previous[...] = image
    for (sw, sh), off in zip(sizes_wh[1:], offsets[1:].tolist(), strict=True):
        level = pixels[off : off + sw * sh].reshape(sh, sw)
        out = cv2.resize(previous, (sw, sh), dst=level, interpolation=cv2.INTER_LINEAR)
        if not np.shares_memory(out, level):  # OpenCV allocated its own output after all
            level[...] = out
        previous = level
    return pixels, offsets, widths, heights


def stereo_matches(
    left: Features,
    right: Features,
    image_left: NDArray[np.uint8],
    image_right: NDArray[np.uint8],
    bf: float,
    fx: float,
    th_orb: int = 75,
    band: float = 2.0,
    window: int = 5,
    slide: int = 5,
    outlier_factor: float = 1.5 * 1.4,
    pyramids: tuple[Pyramid, Pyramid] | None = None,
    pool: Executor | None = None,
) -> tuple[F32, F32]:
    """ORB-SLAM2 ComputeStereoMatches of two rectified images' features (see the module docstring) ->
    (u_right_px (N,), depth_m (N,)) of the left keypoints, NaN where unmatched. bf: baseline x fx (m px); fx: px.
    th_orb: Hamming gate; band: row band half-height in level scales; window: SAD half-window (5: 11 x 11);
    slide: SAD search +-px; outlier_factor: SAD above it x median is an outlier. pyramids: the left and right
    images' :func:`image_pyramid` (``left.n_levels`` levels of ``left.scale_factor``) when the caller has built
    them already (the front end builds each in the thread that extracted the image); None: built here. pool: an
    executor to match half of the keypoints in (the front end's right-image thread, idle by then); the result does
    not depend on it."""
    n = len(left)
    if n == 0 or len(right) == 0:
        return np.full(n, np.nan, np.float32), np.full(n, np.nan, np.float32)
    scales = np.power(float(left.scale_factor), np.arange(left.n_levels, dtype=np.float64))
    if pyramids is None:
        pyramids = (
            image_pyramid(image_left, left.n_levels, left.scale_factor),
            image_pyramid(image_right, left.n_levels, left.scale_factor),
        )
    (pyr_l, offsets, widths, heights), (pyr_r, offsets_r, _, _) = pyramids
    if image_left.shape != image_right.shape or not np.array_equal(offsets, offsets_r):
        raise DatasetError(f"stereo: left image {image_left.shape} and right image {image_right.shape} differ in size")
    if offsets.shape[0] != left.n_levels:
        raise ValueError(f"stereo_matches: pyramids of {offsets.shape[0]} levels for features of {left.n_levels}")
    args = (
        np.ascontiguousarray(left.uv_px, np.float32),
        left.level.astype(np.int64),
        np.ascontiguousarray(left.descriptors),
        np.ascontiguousarray(right.uv_px, np.float32),
        right.level.astype(np.int64),
        np.ascontiguousarray(right.descriptors),
        scales,
        pyr_l,
        pyr_r,
        offsets,
        widths,
        heights,
        float(bf),
        0.0,
        float(fx),  # maxD = bf / minZ with minZ = the baseline
        int(th_orb),
        float(band),
        int(window),
        int(slide),
        _POPCOUNT,
    )
    if pool is None:
        u_right, depth, sad = _stereo_match_kernel(*args, 0, 1)
    else:
        # the odd keypoints in the pool's thread, the even ones here (the kernel holds no GIL); each keypoint's
        # match depends on nothing else, so the merged result is the one-thread one
        future = pool.submit(_stereo_match_kernel, *args, 1, 2)
        u_right, depth, sad = _stereo_match_kernel(*args, 0, 2)
        odd = future.result()
        u_right[1::2], depth[1::2], sad[1::2] = odd[0][1::2], odd[1][1::2], odd[2][1::2]
    matched = np.isfinite(sad)
    if matched.any():
        # step 5: vDistIdx sorted, median = element size / 2, drop SAD >= 1.5 x 1.4 x median
        ordered = np.sort(sad[matched])
        th = outlier_factor * float(ordered[ordered.size // 2])
        bad = matched & (sad >= th)
        u_right[bad] = np.nan
        depth[bad] = np.nan
    return u_right, depth


class StereoFrontEnd(MonocularFrontEnd):
    """Builds the observation record of a rectified stereo pair (``FrameData.image`` and ``image_right``).

    bf: baseline x fx (m px), used only when the front end is not bound to a dataset with a stereo pair
    (``bind_dataset`` takes it from the dataset's ``T_l_r`` and camera). th_depth: close/far threshold in baselines
    (ORB-SLAM2 settings ``ThDepth``; KITTI: 35, EuRoC: 35). The remaining keywords are ComputeStereoMatches'
    constants (see :func:`stereo_matches`).

    matching_pyramid: the level images the SAD windows are read from. "extractor": the pyramid the image's keypoints
    were found on, as ORB-SLAM2 reads its extractor's ``mvImagePyramid`` (for an extractor offering it,
    ``extract_with_pyramid``: slamkit_orb's, whose levels are OpenCV's INTER_LINEAR_EXACT resizes; any other
    extractor: "own"); "own": a pyramid of ORB-SLAM's INTER_LINEAR resizes built for the matching
    (:func:`image_pyramid`), the SAD windows of ORB-SLAM2's own extractor, at the cost of a second pyramid per image.

    parallel: extract the two images at once, the right one in a second thread, each extraction in its own thread
    alone (the extractor's level threads are not used: two threads for the two cores, not four); parallel_matching:
    with ``parallel``, match the odd left keypoints in that thread while the caller's matches the even ones.
    pair_opencv_threads: with ``parallel``, OpenCV's thread count (``cv2.setNumThreads``) while the two extractions
    run, the previous count restored after them; None (the default) leaves OpenCV's setting alone. With OpenCV's
    pool on, one extraction's resizes and blurs take a pool worker, a third runnable thread on a two-core machine
    beside the two extractions; setting 1 removes it, but OpenCV then joins its worker and starts it again at the
    next parallel call, every frame (no gain measured under load; docs/BENCHMARKS.md, branch stspeed2). None of
    these changes the result (OpenCV's resizes and blurs give the same pixels with any thread count).
    """

    uses_depth: ClassVar[bool] = False

    def __init__(
        self,
        extractor: FeatureExtractor,
        init_extractor: FeatureExtractor | None = None,
        bf: float | None = None,
        th_depth: float = 35.0,
        th_orb: int = 75,
        row_band_scales: float = 2.0,
        sad_half_window: int = 5,
        sad_slide_px: int = 5,
        outlier_factor: float = 2.1,
        matching_pyramid: str = "extractor",
        parallel: bool = True,
        parallel_matching: bool = False,
        pair_opencv_threads: int | None = None,
    ) -> None:
        super().__init__(extractor, None)
        del init_extractor  # one-frame initialisation (ORB-SLAM2 builds mpIniORBextractor for monocular only)
        # the same extractor on both images: extractors keep per-thread state (slamkit_orb: a cv2.ORB and FAST
        # detectors per thread), so the two extractions may run at once
        self.right_extractor = extractor
        self.bf = None if bf is None else float(bf)
        self.th_depth = float(th_depth)
        self.th_orb = int(th_orb)
        self.band = float(row_band_scales)
        self.window = int(sad_half_window)
        self.slide = int(sad_slide_px)
        self.outlier_factor = float(outlier_factor)
        if matching_pyramid not in ("extractor", "own"):
            raise ConfigError(f"frontend.matching_pyramid must be 'extractor' or 'own', got {matching_pyramid!r}")
        self.matching_pyramid = matching_pyramid
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="orb-right") if parallel else None
        # half of the stereo matching in that thread too (idle once the right image is extracted)
        self._match_pool = self._pool if parallel_matching else None
        if pair_opencv_threads is not None and (isinstance(pair_opencv_threads, bool) or int(pair_opencv_threads) < 1):
            raise ConfigError(
                f"frontend.pair_opencv_threads must be null or an integer >= 1, got {pair_opencv_threads!r}"
            )
        self.pair_opencv_threads = None if pair_opencv_threads is None else int(pair_opencv_threads)

    def bind_dataset(self, dataset: Any) -> None:
        """Take bf = baseline x fx from the dataset's rectified pair (``T_l_r``'s x translation, the left camera's fx).

        Raises ConfigError when the dataset gives no stereo pair and the config no ``bf``."""
        T_l_r = getattr(dataset, "T_l_r", None)
        if T_l_r is None:
            if self.bf is None:
                raise ConfigError(
                    f"frontend=stereo: dataset {getattr(dataset, 'name', '?')} has no stereo pair (no T_l_r: set "
                    "dataset.stereo=true, or a settings file with Camera.bf / Stereo.b) and frontend.bf is null"
                )
            return
        baseline = abs(float(np.asarray(T_l_r)[0, 3]))
        if not baseline > 0.0:
            raise ConfigError(f"frontend=stereo: dataset {getattr(dataset, 'name', '?')} has a zero stereo baseline")
        self.bf = baseline * float(dataset.camera.K[0, 0])

    def _extract_with_pyramid(
        self, extractor: FeatureExtractor, image: NDArray[np.uint8], camera: Camera, threaded: bool
    ) -> tuple[Features, Pyramid]:
        """The features of one image of the pair and the image's matching pyramid (ComputeStereoMatches' SAD
        levels: the extractor's own, or :func:`image_pyramid`'s built in the calling thread; see the class
        docstring). threaded: let the extractor share the levels out to its own threads."""
        with_pyramid = getattr(extractor, "extract_with_pyramid", None)
        if self.matching_pyramid == "extractor" and with_pyramid is not None:
            features, pyramid = with_pyramid(image, camera, threaded=threaded)
            return features, pyramid.packed()
        features = extractor.extract(image, camera)
        return features, image_pyramid(image, int(features.n_levels), float(features.scale_factor))

    @staticmethod
    def _monocular_record(left: Features, camera: Camera) -> Observations:
        """The left image's record without the right coordinate (the monocular front end's: keypoints in the
        pipeline's image, unit bearings)."""
        if not camera.image_undistorted:
            left = dataclasses.replace(left, uv_undist_px=left.uv_px.copy())
        bearing = camera.unproject_image(left.uv_undist_px.astype(np.float64))
        return Observations.monocular(left, bearing)

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """data.image and data.image_right (H, W) uint8, rectified -> the record with u_right_px and depth_m of the
        left keypoints matched in the right image (NaN elsewhere).

        Raises DatasetError naming the frame when its right image is missing, ConfigError when no bf is known."""
        right_image = data.image_right
        where = data.source or f"frame {data.index}"
        if right_image is None:
            raise DatasetError(
                f"frontend=stereo: frame {data.index} ({where}) has no right image; the dataset must read the pair "
                "(dataset.stereo=true)"
            )
        if self.bf is None:
            raise ConfigError("frontend=stereo: no bf (baseline x fx): bind the front end to a stereo dataset")
        # each image's extraction and its matching pyramid in one thread (the right one in the pool's), each
        # extraction alone in its thread; the left keypoints' monocular record is made while the right image may
        # still be in extraction
        if self._pool is not None:
            opencv_threads = cv2.getNumThreads()
            if self.pair_opencv_threads is not None and self.pair_opencv_threads != opencv_threads:
                cv2.setNumThreads(self.pair_opencv_threads)
            try:
                future = self._pool.submit(self._extract_with_pyramid, self.right_extractor, right_image, camera, False)
                left, pyr_l = self._extract_with_pyramid(self.extractor, data.image, camera, False)
                obs = self._monocular_record(left, camera)
                right, pyr_r = future.result()
            finally:
                if cv2.getNumThreads() != opencv_threads:
                    cv2.setNumThreads(opencv_threads)
        else:
            left, pyr_l = self._extract_with_pyramid(self.extractor, data.image, camera, True)
            obs = self._monocular_record(left, camera)
            right, pyr_r = self._extract_with_pyramid(self.right_extractor, right_image, camera, True)
        fx = float(camera.K[0, 0])
        u_right, depth = stereo_matches(
            left,
            right,
            data.image,
            right_image,
            self.bf,
            fx,
            self.th_orb,
            self.band,
            self.window,
            self.slide,
            self.outlier_factor,
            (pyr_l, pyr_r),
            self._match_pool,
        )
        return dataclasses.replace(
            obs,
            u_right_px=u_right,
            depth_m=depth,
            bf=self.bf,
            th_depth_m=self.bf * self.th_depth / fx,
            sensor="stereo",
        )
