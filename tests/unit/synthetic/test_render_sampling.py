"""The renderer's sampled path (one compiled pass per plane, texels sampled at kept pixels only) against the cv2 path
it replaced (whole-ROI cv2.warpPerspective per mip level, then the z-buffer composite): byte-identical images, depth
and labels; stored checksums of frames rendered before the change; the compiled pixel noise against NumPy's."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest
from numba import njit

from slamkit.io.synthetic import SyntheticDataset
from slamkit.io.synthetic.render import PixelNoise, PlaneRenderer, RenderOutput, _fma32

# sha256 (first 16 hex digits) of frames rendered by main 4c31280's renderer (cv2 path, NumPy noise), computed with
# main's venv (OpenCV 5.0.0) by /work/ref/s18/render/stored_sums.py: (scene, seed, raw frame, stereo) -> arrays.
STORED = {
    ("room", 0, 0, False): {"image": "43a717bd96b5992f", "depth": "2caf8f36ebfba5a0", "labels": "d28af19ff4abefdb"},
    ("room", 0, 415, False): {"image": "99fcffc40c6351b9", "depth": "89bdeb3bf8c185a7", "labels": "d391908a28605669"},
    ("room", 1, 137, False): {"image": "c6e46d6e56df53a0", "depth": "a800ec3a95fa56b7", "labels": "63c3333af9da0a48"},
    ("room", 1, 733, False): {"image": "3566a41318c36f0b", "depth": "4b6c6b153a3fa1c6", "labels": "e34710cf7e79ea1f"},
    ("room", 2, 290, True): {
        "image": "68cef1ba735ce5e2",
        "depth": "421e6f4f435b3a37",
        "labels": "a842fde6c78e69f5",
        "right": "102525feb0eaef92",
    },
    ("long_loop", 0, 1500, False): {
        "image": "ef20718ffbfc8efc",
        "depth": "452e355e7e00689b",
        "labels": "6337a01419a00ddb",
    },
}


# The sampled path reproduces OpenCV 5.0.0's warpPerspective as dispatched on a CPU with AVX2 and FMA3 (its float32
# FMA arithmetic, render.py); on other CPUs or builds the cv2 path's last bits may differ from it (the stored
# checksums below do not depend on cv2 and hold everywhere).
_CV2_AVX2_FMA = (
    cv2.getHardwareFeatureName(11) == "AVX2" and cv2.checkHardwareSupport(11) and cv2.checkHardwareSupport(12)
)
needs_cv2_avx2 = pytest.mark.skipif(
    not (_CV2_AVX2_FMA and cv2.__version__.startswith("5.0")),
    reason=f"the cv2 path's arithmetic is reproduced for OpenCV 5.0 with AVX2+FMA3 (here: OpenCV {cv2.__version__})",
)


def _sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def _legacy(ds: SyntheticDataset) -> PlaneRenderer:
    r = ds.renderer
    return PlaneRenderer(r.scene, r.bank, r.K, r.width, r.height, legacy_cv2=True)


def _assert_same(a: RenderOutput, b: RenderOutput) -> None:
    assert a.grey is not None and b.grey is not None and a.labels is not None and b.labels is not None
    assert np.array_equal(a.grey, b.grey), f"{int((a.grey != b.grey).sum())} grey pixels differ"
    assert np.array_equal(a.depth_m, b.depth_m)
    assert np.array_equal(a.labels, b.labels)


@needs_cv2_avx2
# long_loop (116 planes: ~17 s of textures and cv2 warps) with -m slow; its stored checksums run by default
@pytest.mark.parametrize(
    ("scene", "seed"), [("room", 0), ("room", 3), pytest.param("long_loop", 1, marks=pytest.mark.slow)]
)
def test_sampled_path_is_byte_identical_to_the_cv2_path(scene: str, seed: int) -> None:
    ds = SyntheticDataset(scene=scene, seed=seed, imu=False)
    legacy = _legacy(ds)
    n = len(ds)
    for i in np.linspace(0, n - 1, 9).astype(int):
        T = ds.ground_truth.T_w_c[i]
        _assert_same(ds.renderer.render(T, labels=True), legacy.render(T, labels=True))


@needs_cv2_avx2
def test_sampled_path_matches_off_the_path_and_at_odd_roi_widths() -> None:
    """Poses off the camera path (shifted, tilted) render the same by both paths; their bounding-box widths take
    many residues mod 16, so both of cv2's column regimes (vector body, scalar tail) are exercised."""
    ds = SyntheticDataset(seed=5, imu=False)
    legacy = _legacy(ds)
    rng = np.random.default_rng(3)
    widths: set[int] = set()
    for i in rng.integers(0, len(ds), 12):
        T = ds.ground_truth.T_w_c[i].copy()
        axis = rng.normal(size=3)
        angle = rng.uniform(0.1, 0.6)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / np.linalg.norm(axis)
        T[:3, :3] = T[:3, :3] @ (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K)
        T[:3, 3] += rng.normal(scale=0.4, size=3)
        _assert_same(ds.renderer.render(T, labels=True), legacy.render(T, labels=True))
        for _rp, _, uv in ds.renderer._visible(np.linalg.inv(T)):
            widths.add((min(int(np.ceil(uv[:, 0].max())) + 2, 640) - max(int(np.floor(uv[:, 0].min())) - 1, 0)) % 16)
    assert len(widths) >= 8


@pytest.mark.parametrize(("scene", "seed", "frame", "stereo"), sorted(STORED))
def test_frames_match_checksums_of_the_renderer_before_the_change(
    scene: str, seed: int, frame: int, stereo: bool
) -> None:
    ds = SyntheticDataset(scene=scene, seed=seed, stereo=stereo)
    f = ds[frame]
    labels = ds.render_raw(frame, labels=True).labels
    assert f.depth_m is not None and labels is not None
    got = {"image": _sha(f.image), "labels": _sha(labels)}
    got["depth"] = _sha(f.depth_m)
    if f.image_right is not None:
        got["right"] = _sha(f.image_right)
    assert got == STORED[(scene, seed, frame, stereo)]


@needs_cv2_avx2
def test_colour_frames_keep_the_grey_image_of_the_sampled_path() -> None:
    """With colour on, the renderer draws by the cv2 path; its grey image is the grey-only render's."""
    grey_only = SyntheticDataset(seed=2, imu=False)
    with_colour = SyntheticDataset(seed=2, color=True, imu=False)
    for i in (10, 400):
        a, b = grey_only[i], with_colour[i]
        assert b.color is not None and a.depth_m is not None and b.depth_m is not None
        assert np.array_equal(a.image, b.image)
        assert np.array_equal(a.depth_m, b.depth_m)


@pytest.mark.parametrize("sigma", [0.5, 1.0, 9.0, 40000.0])
def test_compiled_pixel_noise_equals_numpys(sigma: float) -> None:
    """PixelNoise.apply against the NumPy expression it replaced, including clipping and int16 wrap-around."""
    noise = PixelNoise(sigma)
    img = np.random.default_rng(0).integers(0, 256, (37, 53), dtype=np.uint8)
    img[0, :5] = (0, 1, 254, 255, 128)
    got = noise.apply(img, np.random.default_rng(11))
    index = np.frombuffer(np.random.default_rng(11).bytes(2 * img.size), dtype=np.uint16).reshape(img.shape)
    want = np.clip(img.astype(np.int16) + noise._table[index], 0, 255).astype(np.uint8)
    assert got.dtype == np.uint8 and got.shape == img.shape
    assert np.array_equal(got, want)
    colour = np.random.default_rng(1).integers(0, 256, (8, 9, 3), dtype=np.uint8)
    index = np.frombuffer(np.random.default_rng(2).bytes(2 * colour.size), dtype=np.uint16).reshape(colour.shape)
    want = np.clip(colour.astype(np.int16) + noise._table[index], 0, 255).astype(np.uint8)
    assert np.array_equal(noise.apply(colour, np.random.default_rng(2)), want)


def test_fma32_rounds_once() -> None:
    """(1 + 2^-23)(1 - 2^-23) - 1 = -2^-46 exactly: a single rounding keeps it, a float32 product then sum gives 0."""

    @njit
    def fma(a: np.float32, b: np.float32, c: np.float32) -> np.float32:
        return _fma32(a, b, c)

    a, b, c = np.float32(1 + 2**-23), np.float32(1 - 2**-23), np.float32(-1.0)
    assert fma(a, b, c) == np.float32(-(2.0**-46))
    assert np.float32(a * b) + c == 0.0
