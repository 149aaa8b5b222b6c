"""Non-rectified stereo (``frontend=stereo_rig``; ORB-SLAM3 sec. I-B, Campos et al. 2021): two cameras with their
own models (pinhole or Kannala-Brandt fisheye) and a fixed extrinsic ``T_c1_c2`` (the pose of camera 2 in camera 1:
maps camera-2 points into camera 1; ORB-SLAM3's Tlr), keypoints of each image kept as they are (no rectification).

The frame's observation record holds both images' keypoints, camera 1's first (``Observations.n_left``, ORB-SLAM3's
Nleft), each in its own camera's pipeline image. Stereo matches are found as ORB-SLAM3's released code does
(Frame::ComputeStereoFishEyeMatches with KannalaBrandt8::TriangulateMatches; written here for any camera model):

1. the keypoints inside each camera's overlap ("lapping") area, ``lapping_1_px`` / ``lapping_2_px`` = [u_begin,
   u_end] (ORB-SLAM3 settings Camera.lappingBegin/End, Camera2.lappingBegin/End; null: the whole image), are
   brute-force matched by Hamming distance, each camera-1 keypoint taking its two nearest camera-2 keypoints
   (cv2.BFMatcher knnMatch, k = 2), and kept when the best is below ``ratio`` (0.7) times the second;
2. each match is triangulated (linear, from the two bearings) and kept only when the rays' parallax cosine is at
   most ``max_parallax_cos`` (0.9998), the point is in front of both cameras, and its reprojection error in each
   camera's pipeline image is within ``chi2_mono`` (5.991) x the keypoint level's sigma^2 (ORB-SLAM3 checks
   err^2 > 5.991 * sigma2 in each camera).

A kept match links the two keypoints (``stereo_match``), stores the point in camera 1's frame (``xyz_c1``) and gives
the camera-1 keypoint its depth (z in camera 1; ``depth_m``), from which ``th_depth_m`` = baseline x ThDepth splits
close and far points as ORB-SLAM3's mThDepth = mbf * ThDepth / fx with mbf = baseline x fx.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError, DatasetError
from slamkit.features import Features, Observations
from slamkit.frontend.mono import MonocularFrontEnd
from slamkit.geometry.twoview import triangulate_rays
from slamkit.interfaces import Camera, FeatureExtractor
from slamkit.sensors import FrameData

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclasses.dataclass(frozen=True)
class RigMatches:
    """Stereo matches of a non-rectified pair.

    left_to_right: (N1,) int64, the camera-2 keypoint matched to each camera-1 keypoint, -1 for none.
    xyz_c1: (N1, 3) float64 m, the triangulated point of each matched camera-1 keypoint in camera 1; NaN elsewhere.
    """

    left_to_right: I64
    xyz_c1: F64


def _in_lapping(uv: NDArray[np.float32], area: tuple[float, float] | None) -> NDArray[np.bool_]:
    if area is None:
        return np.ones(uv.shape[0], bool)
    return (uv[:, 0] >= area[0]) & (uv[:, 0] <= area[1])


def rig_matches(
    left: Features,
    right: Features,
    camera_1: Camera,
    camera_2: Camera,
    T_c1_c2: F64,
    ratio: float = 0.7,
    max_parallax_cos: float = 0.9998,
    chi2_mono: float = 5.991,
    lapping_1_px: tuple[float, float] | None = None,
    lapping_2_px: tuple[float, float] | None = None,
) -> RigMatches:
    """ORB-SLAM3's stereo matching of a non-rectified pair (see the module docstring).

    left, right: the features of camera 1's and camera 2's images; their ``uv_undist_px`` are in each camera's
    pipeline image (``Camera.project_image``). T_c1_c2: (4, 4) pose of camera 2 in camera 1 (m). ratio: the
    nearest / second-nearest Hamming distance ratio; max_parallax_cos: the rays' largest parallax cosine;
    chi2_mono: the reprojection gate in units of the level's sigma^2 = scale_factor^(2 level).
    """
    n1 = len(left)
    l2r = np.full(n1, -1, np.int64)
    xyz = np.full((n1, 3), np.nan)
    cand1 = np.flatnonzero(_in_lapping(left.uv_undist_px, lapping_1_px))
    cand2 = np.flatnonzero(_in_lapping(right.uv_undist_px, lapping_2_px))
    if cand1.size == 0 or cand2.size < 2:
        return RigMatches(l2r, xyz)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    knn = matcher.knnMatch(
        np.ascontiguousarray(left.descriptors[cand1]), np.ascontiguousarray(right.descriptors[cand2]), k=2
    )
    q: list[int] = []
    t: list[int] = []
    for pair in knn:
        if len(pair) >= 2 and pair[0].distance < pair[1].distance * ratio:
            q.append(int(cand1[pair[0].queryIdx]))
            t.append(int(cand2[pair[0].trainIdx]))
    if not q:
        return RigMatches(l2r, xyz)
    i1 = np.asarray(q, np.int64)
    i2 = np.asarray(t, np.int64)
    T_c1_c2 = np.asarray(T_c1_c2, np.float64)
    T_c2_c1 = np.asarray(np.linalg.inv(T_c1_c2), np.float64)
    r1 = camera_1.unproject_image(left.uv_undist_px[i1].astype(np.float64))
    r2 = camera_2.unproject_image(right.uv_undist_px[i2].astype(np.float64))
    # parallax between the two rays, both in camera 1 (KannalaBrandt8::TriangulateMatches: cosParallaxRays)
    r21 = r2 @ T_c1_c2[:3, :3].T
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_par = np.einsum("ij,ij->i", r1, r21) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r21, axis=1))
    ok = np.isfinite(cos_par) & (cos_par <= max_parallax_cos)
    p1 = triangulate_rays(np.eye(4), T_c2_c1, r1, r2)  # (M, 3) in camera 1
    p2 = p1 @ T_c2_c1[:3, :3].T + T_c2_c1[:3, 3]
    with np.errstate(invalid="ignore"):
        ok &= np.isfinite(p1).all(axis=1) & (p1[:, 2] > 0) & (p2[:, 2] > 0)
    uv1, v1 = camera_1.project_image(np.where(ok[:, None], p1, 1.0))
    uv2, v2 = camera_2.project_image(np.where(ok[:, None], p2, 1.0))
    sigma2_1 = np.power(float(left.scale_factor), 2.0 * left.level[i1].astype(np.float64))
    sigma2_2 = np.power(float(right.scale_factor), 2.0 * right.level[i2].astype(np.float64))
    with np.errstate(invalid="ignore"):
        e1 = np.sum((uv1 - left.uv_undist_px[i1].astype(np.float64)) ** 2, axis=1)
        e2 = np.sum((uv2 - right.uv_undist_px[i2].astype(np.float64)) ** 2, axis=1)
        ok &= v1 & v2 & (e1 <= chi2_mono * sigma2_1) & (e2 <= chi2_mono * sigma2_2)
    # one camera-2 keypoint for one camera-1 keypoint: knnMatch may give the same train keypoint twice (ORB-SLAM3
    # then keeps the last writer in mvRightToLeftMatch while both left keypoints keep it); slamkit keeps the match of
    # least Hamming distance so the record's links are one-to-one
    keep = np.flatnonzero(ok)
    if keep.size:
        dist = _hamming(left.descriptors[i1[keep]], right.descriptors[i2[keep]])
        order = np.lexsort((keep, dist))
        seen: set[int] = set()
        for k in keep[order]:
            j = int(i2[k])
            if j in seen:
                continue
            seen.add(j)
            l2r[i1[k]] = j
            xyz[i1[k]] = p1[k]
    return RigMatches(l2r, xyz)


def _hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> I64:
    """(M,) Hamming distances between rows of a (M, D) and b (M, D) uint8 descriptors."""
    out: I64 = np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(axis=1).astype(np.int64)
    return out


def _lapping(value: Any, key: str) -> tuple[float, float] | None:
    if value is None:
        return None
    items = list(value)
    if len(items) != 2 or not float(items[0]) <= float(items[1]):
        raise ConfigError(f"frontend.{key}: expected [u_begin, u_end] px with u_begin <= u_end, got {value!r}")
    return float(items[0]), float(items[1])


class StereoRigFrontEnd(MonocularFrontEnd):
    """Builds the two-camera observation record of a non-rectified pair (``FrameData.image`` and ``image_right``).

    The cameras and the extrinsic come from the dataset (``bind_dataset``: ``camera`` / ``camera_right`` and
    ``T_l_r``, the pose of camera 2 in camera 1). th_depth: close/far threshold in baselines (ORB-SLAM3 ThDepth;
    EuRoC: 35). ratio, max_parallax_cos, chi2_mono, lapping_1_px, lapping_2_px: see :func:`rig_matches`.
    """

    uses_depth: ClassVar[bool] = False
    #: Each frame needs its second image (``System.track(..., right=...)``).
    uses_right: ClassVar[bool] = True
    #: Its records hold two cameras' keypoints (``Observations.n_left``): a consumer that does not read them refuses it.
    two_cameras: ClassVar[bool] = True

    def __init__(
        self,
        extractor: FeatureExtractor,
        init_extractor: FeatureExtractor | None = None,
        th_depth: float = 35.0,
        ratio: float = 0.7,
        max_parallax_cos: float = 0.9998,
        chi2_mono: float = 5.991,
        lapping_1_px: Any = None,
        lapping_2_px: Any = None,
        parallel: bool = True,
    ) -> None:
        super().__init__(extractor, None)
        del init_extractor  # one-frame initialisation, as the rectified stereo front end
        self.right_extractor = extractor
        self.th_depth = float(th_depth)
        self.ratio = float(ratio)
        self.max_parallax_cos = float(max_parallax_cos)
        self.chi2_mono = float(chi2_mono)
        self.lapping_1 = _lapping(lapping_1_px, "lapping_1_px")
        self.lapping_2 = _lapping(lapping_2_px, "lapping_2_px")
        self.camera_2: Camera | None = None
        self.T_c1_c2: F64 | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="orb-cam2") if parallel else None

    def bind_rig(self, camera_2: Camera, T_c1_c2: F64) -> None:
        """Set the second camera and its pose in camera 1 (4, 4) m. Raises ConfigError on a zero baseline."""
        T = np.asarray(T_c1_c2, np.float64).reshape(4, 4)
        if not np.linalg.norm(T[:3, 3]) > 0.0:
            raise ConfigError("frontend=stereo_rig: the two cameras are at the same place (zero baseline)")
        self.camera_2 = camera_2
        self.T_c1_c2 = T

    def bind_dataset(self, dataset: Any) -> None:
        """Take the second camera and T_c1_c2 from the dataset (``camera_right``, ``T_l_r``).

        Raises ConfigError when the dataset has no second camera."""
        cam2 = getattr(dataset, "camera_right", None)
        T = getattr(dataset, "T_l_r", None)
        if cam2 is None or T is None:
            raise ConfigError(
                f"frontend=stereo_rig: dataset {getattr(dataset, 'name', '?')} has no second camera (camera_right and "
                "T_l_r): set dataset.stereo=true"
            )
        self.bind_rig(cam2, np.asarray(T))

    @property
    def baseline_m(self) -> float:
        """|t| of T_c1_c2, m (0 before the rig is bound)."""
        return 0.0 if self.T_c1_c2 is None else float(np.linalg.norm(self.T_c1_c2[:3, 3]))

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """data.image (camera 1) and data.image_right (camera 2), (H, W) uint8 each as the cameras took them ->
        the two-camera record (camera 1's keypoints, then camera 2's; ``n_left``, ``stereo_match``, ``xyz_c1``).

        Raises DatasetError naming the frame when its second image is missing, ConfigError before ``bind_rig``."""
        image_2 = data.image_right
        if image_2 is None:
            raise DatasetError(
                f"frontend=stereo_rig: frame {data.index} ({data.source or '?'}) has no second image; the dataset "
                "must read the pair (dataset.stereo=true)"
            )
        if self.camera_2 is None or self.T_c1_c2 is None:
            raise ConfigError("frontend=stereo_rig: no second camera: bind the front end to a stereo dataset")
        cam2 = self.camera_2
        if self._pool is not None:
            future = self._pool.submit(self.right_extractor.extract, image_2, cam2)
            left = self.extractor.extract(data.image, camera)
            right = future.result()
        else:
            left = self.extractor.extract(data.image, camera)
            right = self.right_extractor.extract(image_2, cam2)
        if not camera.image_undistorted:
            left = dataclasses.replace(left, uv_undist_px=left.uv_px.copy())
        if not cam2.image_undistorted:
            right = dataclasses.replace(right, uv_undist_px=right.uv_px.copy())
        return rig_observations(
            left,
            right,
            camera,
            cam2,
            self.T_c1_c2,
            self.th_depth,
            self.ratio,
            self.max_parallax_cos,
            self.chi2_mono,
            self.lapping_1,
            self.lapping_2,
        )


def rig_observations(
    left: Features,
    right: Features,
    camera_1: Camera,
    camera_2: Camera,
    T_c1_c2: F64,
    th_depth: float = 35.0,
    ratio: float = 0.7,
    max_parallax_cos: float = 0.9998,
    chi2_mono: float = 5.991,
    lapping_1_px: tuple[float, float] | None = None,
    lapping_2_px: tuple[float, float] | None = None,
) -> Observations:
    """The two-camera record of features ``left`` (camera 1) and ``right`` (camera 2), their ``uv_undist_px`` in
    each camera's pipeline image: camera 1's keypoints then camera 2's, bearings in each keypoint's own camera, the
    stereo matches of :func:`rig_matches` (``stereo_match``, ``xyz_c1``, camera 1's ``depth_m``)."""
    n1, n2 = len(left), len(right)
    m = rig_matches(
        left, right, camera_1, camera_2, T_c1_c2, ratio, max_parallax_cos, chi2_mono, lapping_1_px, lapping_2_px
    )
    link = np.full(n1 + n2, -1, np.int64)
    matched = np.flatnonzero(m.left_to_right >= 0)
    link[matched] = n1 + m.left_to_right[matched]
    link[n1 + m.left_to_right[matched]] = matched
    xyz = np.full((n1 + n2, 3), np.nan)
    xyz[matched] = m.xyz_c1[matched]
    xyz[n1 + m.left_to_right[matched]] = m.xyz_c1[matched]
    depth = np.full(n1 + n2, np.nan, np.float32)
    depth[matched] = m.xyz_c1[matched, 2].astype(np.float32)
    bearing = np.concatenate(
        [
            camera_1.unproject_image(left.uv_undist_px.astype(np.float64)).reshape(n1, 3),
            camera_2.unproject_image(right.uv_undist_px.astype(np.float64)).reshape(n2, 3),
        ]
    )
    baseline = float(np.linalg.norm(np.asarray(T_c1_c2, np.float64)[:3, 3]))
    fx = float(camera_1.K[0, 0])
    return Observations(
        uv_px=np.concatenate([left.uv_px, right.uv_px]).astype(np.float32),
        uv_undist_px=np.concatenate([left.uv_undist_px, right.uv_undist_px]).astype(np.float32),
        level=np.concatenate([left.level, right.level]).astype(np.int32),
        angle_deg=np.concatenate([left.angle_deg, right.angle_deg]).astype(np.float32),
        response=np.concatenate([left.response, right.response]).astype(np.float32),
        descriptors=np.concatenate([left.descriptors, right.descriptors]),
        scale_factor=left.scale_factor,
        n_levels=left.n_levels,
        bearing=bearing,
        u_right_px=np.full(n1 + n2, np.nan, np.float32),
        depth_m=depth,
        bf=baseline * fx,
        th_depth_m=baseline * float(th_depth),
        sensor="stereo",
        n_left=n1,
        stereo_match=link,
        xyz_c1=xyz,
        camera_2=camera_2,
        T_c2_c1=np.asarray(np.linalg.inv(np.asarray(T_c1_c2, np.float64)), np.float64),
    )
