"""How good a vocabulary is at place recognition: top-1 retrieval precision against ground-truth poses.

Protocol (``retrieval_precision``): every ``step``-th frame of a sequence is a keyframe in the database;
every frame halfway between two keyframes is a query. A query is answered by the database's best-scoring
keyframe; the answer is right when it is one of the two keyframes nearest to the query in camera
position among those whose optical axis is within ``max_angle_deg`` of the query's (the two keyframes
that bracket it, on a smooth path). Frames within ``exclude_recent`` keyframes of the query can be left
out of the database to measure loop detection: on a revisit, the right answer is the place seen a loop ago.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import FeatureExtractor
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.vocabulary import Vocabulary

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class RetrievalResult:
    """n_queries queries, n_correct answered right; precision = n_correct / n_queries.
    n_near: answers within ``near_m`` of the query camera and looking within 45 deg of it (the same place,
    if not one of the two nearest keyframes). margin: median over queries of the best score of a right
    keyframe / the best score of any other."""

    n_queries: int
    n_correct: int
    n_near: int
    margin: float

    @property
    def precision(self) -> float:
        return self.n_correct / self.n_queries if self.n_queries else float("nan")


def right_keyframes(
    T_w_c_query: F64,
    T_w_c_kfs: F64,
    allowed: NDArray[np.bool_] | None = None,
    max_angle_deg: float = 45.0,
    n: int = 2,
) -> list[int]:
    """Indices of the ``n`` keyframes nearest to the query camera in position among the ``allowed`` ones
    (default: all) looking within ``max_angle_deg`` of its direction. T_w_c_query: (4, 4);
    T_w_c_kfs: (K, 4, 4); allowed: (K,) bool."""
    d = np.linalg.norm(T_w_c_kfs[:, :3, 3] - T_w_c_query[:3, 3], axis=1)
    cos = T_w_c_kfs[:, :3, 2] @ T_w_c_query[:3, 2]
    ok = cos >= np.cos(np.radians(max_angle_deg))
    if allowed is not None:
        ok &= allowed
    d = np.where(ok, d, np.inf)
    order = np.argsort(d, kind="stable")[:n]
    return [int(i) for i in order if np.isfinite(d[i])]


def retrieval_precision(
    vocab: Vocabulary,
    descriptors: Sequence[NDArray[np.uint8]],
    T_w_c: F64,
    step: int,
    query_frames: Sequence[int] | None = None,
    exclude_recent: int = 0,
    direct_index_level: int = 2,
    near_m: float = 1.0,
) -> RetrievalResult:
    """Top-1 retrieval precision over one sequence.

    descriptors: one (N_j, 32) array per frame j; T_w_c: (F, 4, 4) ground-truth poses of the frames.
    Keyframes are frames 0, step, 2 step, ...; queries default to the frames halfway between them.
    exclude_recent: keyframes whose index is within this many keyframes before the query are not
    candidates (0: all keyframes are).
    """
    n = len(descriptors)
    kf_frames = list(range(0, n, step))
    queries = (
        list(query_frames) if query_frames is not None else [f + step // 2 for f in kf_frames if f + step // 2 < n]
    )
    db = KeyframeDatabase(vocab.score)
    for kf, f in enumerate(kf_frames):
        db.add(kf, vocab.transform(descriptors[f], direct_index_level))
    T_kfs = T_w_c[kf_frames]
    correct = near = 0
    margins = []
    for q in queries:
        last_kf = q // step
        exclude = range(max(0, last_kf - exclude_recent + 1), last_kf + 1) if exclude_recent else ()
        allowed = np.ones(len(kf_frames), bool)
        allowed[list(exclude)] = False
        right = right_keyframes(T_w_c[q], T_kfs, allowed)
        ranked = db.query(vocab.transform(descriptors[q], direct_index_level), exclude=list(exclude))
        if ranked and ranked[0][0] in right:
            correct += 1
        if ranked:
            T_top = T_kfs[ranked[0][0]]
            close = np.linalg.norm(T_top[:3, 3] - T_w_c[q][:3, 3]) <= near_m
            if close and T_top[:3, 2] @ T_w_c[q][:3, 2] >= np.cos(np.radians(45.0)):
                near += 1
        wrong_scores = [s for kf, s in ranked if kf not in right]
        right_scores = [s for kf, s in ranked if kf in right]
        if right_scores and wrong_scores and wrong_scores[0] > 0:
            margins.append(right_scores[0] / wrong_scores[0])
    return RetrievalResult(len(queries), correct, near, float(np.median(margins)) if margins else float("nan"))


@dataclass(frozen=True)
class EvalSequence:
    """Descriptors of the frames of one evaluation sequence and their ground-truth poses (F, 4, 4)."""

    name: str
    descriptors: list[NDArray[np.uint8]]
    T_w_c: F64


def dataset_sequence(name: str, dataset: Iterable[Any], extractor: FeatureExtractor, every: int = 1) -> EvalSequence:
    """Extract every ``every``-th frame of a slamkit Dataset that has ground truth (frames without are skipped)."""
    descs: list[NDArray[np.uint8]] = []
    poses: list[F64] = []
    for j, frame in enumerate(dataset):
        if j % every or frame.T_w_c_gt is None:
            continue
        descs.append(np.ascontiguousarray(extractor.extract(frame.image).descriptors, np.uint8))
        poses.append(np.asarray(frame.T_w_c_gt, np.float64))
    return EvalSequence(name, descs, np.stack(poses) if poses else np.zeros((0, 4, 4)))


def synthetic_sequence(scene: str, seed: int, extractor: FeatureExtractor, every: int = 15) -> EvalSequence:
    """Every ``every``-th frame (default: 2 per second) of synthetic scene ``scene`` with texture seed ``seed``."""
    from slamkit.io.synthetic.dataset import SyntheticDataset

    ds = SyntheticDataset(scene=scene, seed=seed, imu=False, depth=False, skip=None)
    idx = range(0, len(ds), every)
    descs = [np.ascontiguousarray(extractor.extract(ds[i].image).descriptors, np.uint8) for i in idx]
    return EvalSequence(f"synthetic/{scene} (seed {seed})", descs, ds.ground_truth.T_w_c[list(idx)])


def real_sequences(root: Path, extractor: FeatureExtractor) -> list[tuple[EvalSequence, int]]:
    """The real sequences of the shared datasets folder that are present, with the keyframe step used:
    EuRoC V1_01_easy cam0 (95 frames, 20 Hz; keyframe every 10), KITTI 07 (every 4) (160 frames, 10 Hz), TUM fr1/xyz (10 frames)."""
    from slamkit.io.euroc import EurocDataset
    from slamkit.io.kitti import KittiDataset
    from slamkit.io.tum_rgbd import TumRgbdDataset

    out: list[tuple[EvalSequence, int]] = []
    euroc = root / "euroc" / "V1_01_easy"
    if euroc.is_dir():
        gt = euroc / "extra" / "V101_gt_evo_tum_format.txt"
        ds = EurocDataset(euroc, groundtruth=gt if gt.is_file() else None, imu=False)
        out.append((dataset_sequence("euroc/V1_01_easy", ds, extractor), 10))
    kitti = root / "kitti"
    if (kitti / "sequences" / "07").is_dir():
        out.append((dataset_sequence("kitti/07", KittiDataset(kitti, "07"), extractor), 4))
    tum = root / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz_first10"
    if tum.is_dir():
        out.append((dataset_sequence("tum/fr1_xyz (10 frames)", TumRgbdDataset(tum, use_depth=False), extractor), 2))
    return out
