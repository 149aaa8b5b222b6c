"""The seams of slamkit: what a component must provide to be swapped in by config.

Each interface is a ``typing.Protocol`` (runtime-checkable, so the plugin manager can verify that a
component a plugin returns really is what its kind promises). Components exchange plain data only:
images and arrays (``slamkit.sensors``, ``slamkit.features``) and optimization problems/results
(``slamkit.problems``). See docs/conventions.md for frames and units; in short ``T_a_b`` maps points
from frame b to frame a, poses are float64, pixels float32, metres/radians/seconds.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, cast, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Features, Observations
from slamkit.problems import (
    BundleProblem,
    BundleResult,
    EssentialGraphProblem,
    EssentialGraphResult,
    PoseOnlyProblem,
    PoseOnlyResult,
    Sim3Problem,
    Sim3Result,
)
from slamkit.sensors import FrameData, Trajectory

F64 = NDArray[np.float64]


@runtime_checkable
class Camera(Protocol):
    """A central camera model (pinhole with radial-tangential distortion, Kannala-Brandt fisheye, ...).

    Pixel coordinates are of the raw (distorted) image unless a name says ``undist``.
    """

    model: str
    width: int
    height: int

    @property
    def K(self) -> F64:
        """(3, 3) intrinsic matrix of the ideal pinhole image (fx, fy, cx, cy), px."""
        ...

    @property
    def dist(self) -> F64:
        """Distortion coefficients of the model: pinhole (5,) k1, k2, p1, p2, k3; Kannala-Brandt (4,) k1..k4."""
        ...

    def project(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m in the camera frame (z forward) -> (N, 2) px in the raw image."""
        ...

    def unproject(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 3) unit bearing vectors in the camera frame."""
        ...

    def undistort_points(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 2) px in the ideal pinhole image with the same K."""
        ...

    # The pipeline's image: where keypoints are matched and map points projected (``Observations.uv_undist_px``).
    # A pinhole camera's is the undistorted pinhole image (ORB-SLAM2/3); a fisheye camera's is the raw image
    # (ORB-SLAM3's Kannala-Brandt). The pipeline never assumes a pinhole: it projects through these.

    #: True when the pipeline's image is the undistorted pinhole image, False when it is the raw image.
    image_undistorted: bool

    def image_bounds(self) -> tuple[float, float, float, float]:
        """(min_u, max_u, min_v, max_v) px: where a point of the pipeline's image counts as inside the image."""
        ...

    def project_image(self, xyz_c: F64) -> tuple[F64, NDArray[np.bool_]]:
        """xyz_c: (N, 3) m camera frame -> (uv (N, 2) px in the pipeline's image, valid (N,) bool: in front of the
        camera (z > 0) and within the model's field of view)."""
        ...

    def unproject_image(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) px in the pipeline's image -> (N, 3) unit bearings in the camera frame."""
        ...

    def project_image_jacobian(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m camera frame -> (N, 2, 3) d uv / d xyz_c of ``project_image``, px/m."""
        ...


@runtime_checkable
class Dataset(Protocol):
    """A sequence of timestamped sensor packets with its calibration and, when known, ground truth.

    camera: the (left) camera. camera_right / T_l_r: the right camera of a stereo pair and the pose of the
    right camera in the left camera frame (maps right-camera points to left). T_b_c: pose of the (left)
    camera in the IMU/body frame. ground_truth: camera poses T_w_c over time, or None.

    Optional: ``prepare_playback()``, which the threaded runner calls before its clock starts, for one-off
    work that should not land on the first frames of a timed run (the synthetic world makes its textures).
    """

    name: str
    camera: Camera
    camera_right: Camera | None
    T_l_r: F64 | None
    T_b_c: F64 | None
    fps: float
    ground_truth: Trajectory | None

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[FrameData]: ...


@runtime_checkable
class FeatureExtractor(Protocol):
    """Detects keypoints and computes binary descriptors on a grey image."""

    n_levels: int
    scale_factor: float

    def extract(self, image: NDArray[np.uint8], camera: Camera | None = None) -> Features:
        """image: (H, W) uint8 grey. With a camera, ``uv_undist_px`` are undistorted through it."""
        ...


@runtime_checkable
class FrontEnd(Protocol):
    """Turns a sensor packet into the frame's per-keypoint observation record (config group ``frontend``).

    Monocular (``frontend=mono``) extracts features of the (left) image; stereo and RGB-D front ends fill the
    record's ``u_right_px`` / ``depth_m`` / ``bf`` from the right image or the depth map. A front end owns its
    feature extractor(s): ``initializing`` asks for the frames of a monocular initialisation, on which ORB-SLAM
    extracts more features (ORB-SLAM2: 2x, ORB-SLAM3: 5x; ``pipeline.tracking.init_feature_factor``).

    Optional class attribute ``uses_depth`` (default False): whether the front end reads ``FrameData.depth_m``; a
    dataset whose ``use_depth`` is null reads depth maps only for such a front end (slamkit.app).
    """

    @property
    def n_levels(self) -> int:
        """Pyramid levels of the extractor (ORB-SLAM: 8)."""
        ...

    @property
    def scale_factor(self) -> float:
        """Scale between pyramid levels (ORB-SLAM: 1.2)."""
        ...

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """data: one packet of the dataset; camera: the (left) camera -> the record of every keypoint."""
        ...

    def warm_up(self, camera: Camera) -> None:
        """Run the extractor(s) once on a synthetic image of the camera's size (loads compiled kernels)."""
        ...


def _frozen(array: NDArray[Any]) -> NDArray[Any]:
    array.setflags(write=False)
    return array


def _position_of(keys: NDArray[np.int32], key: object) -> int:
    """Index of ``key`` in the strictly ascending ``keys`` (K,), or -1 when absent or not an integer (a bool is not
    a word or node id): the lookup behind WordWeights' and DirectIndex's Mapping interface."""
    if isinstance(key, bool) or not isinstance(key, int | np.integer):
        return -1
    at = int(np.searchsorted(keys, key))
    return at if at < keys.shape[0] and int(keys[at]) == int(key) else -1


class WordWeights(Mapping[int, float]):
    """A bag of words' weights as two arrays: a read-only ``Mapping`` word id -> weight, iterated in ascending id.

    ids: (K,) int32 word ids, strictly ascending. weights: (K,) float64, each word's weight.
    12 bytes a word (a dict of Python ints and floats costs ~100): a keyframe's ~900 words are its largest part after
    its features (docs/BENCHMARKS.md, "Memory per keyframe"). Both arrays are read-only.
    """

    __slots__ = ("ids", "weights")

    def __init__(self, ids: NDArray[np.integer], weights: NDArray[np.floating]) -> None:
        i = np.array(ids, np.int32, copy=True).reshape(-1)
        w = np.array(weights, np.float64, copy=True).reshape(-1)
        if i.shape != w.shape:
            raise ValueError(f"WordWeights: {i.shape[0]} ids but {w.shape[0]} weights")
        if i.size > 1 and not bool(np.all(i[1:] > i[:-1])):
            raise ValueError("WordWeights: word ids must be strictly ascending")
        self.ids: NDArray[np.int32] = _frozen(i)
        self.weights: NDArray[np.float64] = _frozen(w)

    @classmethod
    def of(cls, words: Mapping[int, float]) -> WordWeights:
        """``words`` itself if it is a WordWeights, else its items sorted by word id."""
        if isinstance(words, WordWeights):
            return words
        keys = np.fromiter((int(k) for k in words), np.int64, len(words))
        vals = np.fromiter((float(words[k]) for k in words), np.float64, len(words))
        order = np.argsort(keys, kind="stable")
        return cls(keys[order], vals[order])

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __iter__(self) -> Iterator[int]:
        return iter(self.ids.tolist())

    def __contains__(self, word: object) -> bool:
        return self._find(word) >= 0

    def __getitem__(self, word: int) -> float:
        at = self._find(word)
        if at < 0:
            raise KeyError(word)
        return float(self.weights[at])

    def _find(self, word: object) -> int:
        return _position_of(self.ids, word)

    def items(self) -> Iterator[tuple[int, float]]:  # type: ignore[override]
        """(word, weight) pairs in ascending word id."""
        return zip(self.ids.tolist(), self.weights.tolist(), strict=True)

    def values(self) -> list[float]:  # type: ignore[override]
        """The weights in ascending word id."""
        return list(self.weights.tolist())

    def __reduce__(self) -> tuple[Any, ...]:
        return (WordWeights, (self.ids, self.weights))

    def __repr__(self) -> str:
        return f"WordWeights({len(self)} words)"


class DirectIndex(Mapping[int, NDArray[np.int32]]):
    """A direct index as three arrays (CSR): a read-only ``Mapping`` node id -> (k,) int32 feature indices,
    iterated in ascending node id.

    nodes: (G,) int32 node ids, strictly ascending. offsets: (G + 1,) int64, node g's features are
    ``features[offsets[g]:offsets[g + 1]]``. features: (M,) int32 feature indices of the image. Read-only arrays.
    """

    __slots__ = ("features", "nodes", "offsets")

    def __init__(self, nodes: NDArray[np.integer], offsets: NDArray[np.integer], features: NDArray[np.integer]) -> None:
        n = np.array(nodes, np.int32, copy=True).reshape(-1)
        o = np.array(offsets, np.int64, copy=True).reshape(-1)
        f = np.array(features, np.int32, copy=True).reshape(-1)
        if o.shape != (n.size + 1,) or o[0] != 0 or o[-1] != f.size or bool(np.any(np.diff(o) < 0)):
            raise ValueError(f"DirectIndex: offsets must be (G + 1,) = ({n.size + 1},) from 0 to {f.size}, ascending")
        if n.size > 1 and not bool(np.all(n[1:] > n[:-1])):
            raise ValueError("DirectIndex: node ids must be strictly ascending")
        self.nodes: NDArray[np.int32] = _frozen(n)
        self.offsets: NDArray[np.int64] = _frozen(o)
        self.features: NDArray[np.int32] = _frozen(f)

    @classmethod
    def of(cls, groups: Mapping[int, NDArray[np.integer]]) -> DirectIndex:
        """``groups`` itself if it is a DirectIndex, else its groups in ascending node id (each group's order kept)."""
        if isinstance(groups, DirectIndex):
            return groups
        nodes = sorted(int(k) for k in groups)
        parts = [np.asarray(groups[k], np.int64).reshape(-1) for k in nodes]
        offsets = np.zeros(len(nodes) + 1, np.int64)
        np.cumsum([p.size for p in parts], out=offsets[1:])
        feats = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        return cls(np.array(nodes, np.int64), offsets, feats)

    def __len__(self) -> int:
        return int(self.nodes.shape[0])

    def __iter__(self) -> Iterator[int]:
        return iter(self.nodes.tolist())

    def __contains__(self, node: object) -> bool:
        return self._find(node) >= 0

    def __getitem__(self, node: int) -> NDArray[np.int32]:
        at = self._find(node)
        if at < 0:
            raise KeyError(node)
        return self.features[self.offsets[at] : self.offsets[at + 1]]

    def _find(self, node: object) -> int:
        return _position_of(self.nodes, node)

    def items(self) -> Iterator[tuple[int, NDArray[np.int32]]]:  # type: ignore[override]
        """(node, its features) in ascending node id."""
        o = self.offsets.tolist()
        return ((n, self.features[o[g] : o[g + 1]]) for g, n in enumerate(self.nodes.tolist()))

    def values(self) -> list[NDArray[np.int32]]:  # type: ignore[override]
        """Each node's features, in ascending node id."""
        return [v for _, v in self.items()]

    def __reduce__(self) -> tuple[Any, ...]:
        return (DirectIndex, (self.nodes, self.offsets, self.features))

    def __repr__(self) -> str:
        return f"DirectIndex({len(self)} nodes, {self.features.shape[0]} features)"


_NO_WORDS = WordWeights(np.zeros(0, np.int32), np.zeros(0, np.float64))
_NO_DIRECT_INDEX = DirectIndex(np.zeros(0, np.int32), np.zeros(1, np.int64), np.zeros(0, np.int32))


@dataclass(frozen=True)
class BowDescription:
    """A bag-of-words description of one image.

    words: word id -> TF-IDF weight (L1-normalised), stored as a ``WordWeights`` (arrays, ascending word id).
    direct_index: the recognizer's own grouping of the image's features (DBoW: vocabulary node id at the
        configured level -> (k,) indices of the image's features; empty for a recognizer without one), stored as a
        ``DirectIndex`` (CSR arrays, ascending node id). Only the recognizer that made it reads it (its ``match`` and
        ``candidate_pairs``); the pipeline never does.
    Any mappings given are converted (sorted by id) when the description is made, so every description a keyframe
    holds is compact: ~13 KB for 1000 features, where dicts of Python numbers took ~110 KB.
    """

    words: Mapping[int, float] = field(default_factory=lambda: _NO_WORDS)
    direct_index: Mapping[int, NDArray[np.integer]] = field(default_factory=lambda: _NO_DIRECT_INDEX)

    def __post_init__(self) -> None:
        words = _NO_WORDS if not self.words else WordWeights.of(self.words)
        direct = _NO_DIRECT_INDEX if not self.direct_index else DirectIndex.of(self.direct_index)
        object.__setattr__(self, "words", words)
        object.__setattr__(self, "direct_index", direct)

    @property
    def word_weights(self) -> WordWeights:
        """``words`` as its arrays (typed)."""
        return cast(WordWeights, self.words)

    @property
    def direct(self) -> DirectIndex:
        """``direct_index`` as its arrays (typed)."""
        return cast(DirectIndex, self.direct_index)


#: (keyframe id, n) -> its n best covisible keyframes, best first (``store.covisibility.best_neighbors``).
NeighborsFn = Callable[[int, int], Sequence[int]]


@runtime_checkable
class PlaceRecognizer(Protocol):
    """A visual vocabulary and keyframe database for relocalization and loop detection (ORB-SLAM III-E)."""

    def transform(self, descriptors: NDArray[np.uint8]) -> BowDescription:
        """descriptors: (N, D) uint8 -> the image's bag of words and direct index."""
        ...

    def score(self, a: BowDescription, b: BowDescription) -> float:
        """Similarity in [0, 1] (L1 score for DBoW2)."""
        ...

    def add(self, keyframe_id: int, bow: BowDescription) -> None:
        """Insert a keyframe in the inverted index."""
        ...

    def remove(self, keyframe_id: int) -> None:
        """Erase a keyframe from the inverted index (keyframe culling)."""
        ...

    def query(self, bow: BowDescription, exclude: Sequence[int] = ()) -> list[tuple[int, float]]:
        """Keyframes sharing at least one word with ``bow`` (not in ``exclude``) with their scores,
        best first."""
        ...

    def loop_candidates(
        self, bow: BowDescription, connected: Collection[int], min_score: float, neighbors: NeighborsFn
    ) -> list[tuple[int, float]]:
        """Loop candidates of a keyframe (ORB-SLAM III-E / VII-A): keyframes not in ``connected`` scoring at least
        ``min_score``, grouped with their covisible ``neighbors`` and kept when their group scores above 75% of
        the best group. Returns (keyframe id, score), best first."""
        ...

    def relocalization_candidates(self, bow: BowDescription, neighbors: NeighborsFn) -> list[tuple[int, float]]:
        """Relocalization candidates of a frame (ORB-SLAM V-C): as loop candidates, without a score floor."""
        ...

    def match(
        self,
        feats1: Features,
        bow1: BowDescription,
        feats2: Features,
        bow2: BowDescription,
        ratio: float,
        mask1: NDArray[np.bool_] | None = None,
        mask2: NDArray[np.bool_] | None = None,
        *,
        max_distance: int,
        rotation_bins: int | None,
    ) -> NDArray[np.int64]:
        """BoW-guided matching (ORB-SLAM SearchByBoW): (K, 2) feature index pairs (image 1, image 2) among features
        sharing a vocabulary node, best Hamming distance <= ``max_distance`` bits, nearest/second ``ratio`` test,
        each feature of image 2 once, and rotation consistency over ``rotation_bins`` histogram bins (None: no
        check); masks restrict the eligible features. The caller passes the thresholds (pipeline.matcher)."""
        ...

    def candidate_pairs(
        self,
        feats1: Features,
        bow1: BowDescription,
        feats2: Features,
        bow2: BowDescription,
        mask1: NDArray[np.bool_] | None = None,
        mask2: NDArray[np.bool_] | None = None,
        *,
        max_distance: int,
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """The BoW-restricted candidates of ORB-SLAM SearchForTriangulation (local mapping, VI-C): every pair
        (feature a of image 1, feature b of image 2) that the recognizer's structure puts together (DBoW: the same
        vocabulary node of the direct index, ORB-SLAM's FeatureVector walk), both allowed by the masks ((N1,) /
        (N2,) bool, None: all), with Hamming distance <= ``max_distance`` bits (pipeline.matcher.th_low), each pair
        once -> (a, b, distance) (K,) int64 arrays. Local mapping filters them (epipolar constraint, best per
        feature, one-to-one, rotation), so the order does not change its result; DBoW gives node order, then a,
        then b. A recognizer with no such structure may return every masked pair within ``max_distance``
        (slamkit.pipeline.matching.close_pairs): correct, only slower. Every pair ``match`` returns under the same
        masks and ``max_distance`` is among these."""
        ...


@dataclass(frozen=True)
class TwoViewResult:
    """Outcome of a map initialisation attempt from two views.

    success: False when the initializer refused (``reason`` says why: low parallax, ambiguity, ...).
    model: "H" (homography) or "F" (fundamental) — which model explained the scene.
    T_cur_ref: (4, 4) pose of the reference camera in the current camera (maps ref points to cur), with
        an arbitrary scale (the pipeline rescales the map).
    xyz_ref: (M, 3) m points in the reference camera frame, one per input match (NaN where not triangulated).
    triangulated: (M,) bool, which matches gave a good point.
    """

    success: bool
    reason: str
    model: Literal["H", "F", ""] = ""
    T_cur_ref: F64 | None = None
    xyz_ref: F64 | None = None
    triangulated: NDArray[np.bool_] | None = None
    details: Mapping[str, Any] | None = None


@runtime_checkable
class Initializer(Protocol):
    """Builds an initial two-view reconstruction from feature matches (ORB-SLAM section IV)."""

    def initialize(
        self,
        uv_ref_px: F64,
        uv_cur_px: F64,
        K: F64,
        rng: np.random.Generator,
    ) -> TwoViewResult:
        """uv_ref_px, uv_cur_px: (M, 2) undistorted matched keypoints; K: (3, 3)."""
        ...


class AbortToken(Protocol):
    """Anything with ``is_set()``: threading.Event, multiprocessing.Event, or slamkit's own token."""

    def is_set(self) -> bool: ...


@runtime_checkable
class Optimizer(Protocol):
    """Every optimization ORB-SLAM performs. Takes plain problems, returns plain results; never the map."""

    name: str

    def optimize_pose(self, problem: PoseOnlyProblem) -> PoseOnlyResult:
        """Motion-only BA with ORB-SLAM's rounds of chi-square outlier classification."""
        ...

    def bundle_adjust(self, problem: BundleProblem, abort: AbortToken | None = None) -> BundleResult:
        """Local/global BA; checks ``abort`` between iterations and returns a valid partial result."""
        ...

    def optimize_sim3(self, problem: Sim3Problem) -> Sim3Result:
        """Relative Sim3 from matched points with the bidirectional reprojection error."""
        ...

    def optimize_essential_graph(self, problem: EssentialGraphProblem) -> EssentialGraphResult:
        """Pose-graph optimization in Sim3 (or SE3) over the essential graph."""
        ...


# The MapStore protocol (and its graph views) has a module of its own; re-exported here with the other seams.
from slamkit.map.protocol import CovisibilityGraphView as CovisibilityGraphView  # noqa: E402
from slamkit.map.protocol import MapStore as MapStore  # noqa: E402
from slamkit.map.protocol import SpanningTreeView as SpanningTreeView  # noqa: E402

#: kind (= Hydra config group) -> the protocol a component of that kind must satisfy.
KIND_PROTOCOLS: dict[str, type] = {
    "features": FeatureExtractor,
    "frontend": FrontEnd,
    "place": PlaceRecognizer,
    "initializer": Initializer,
    "optimizer": Optimizer,
    "map": MapStore,
    "dataset": Dataset,
}
