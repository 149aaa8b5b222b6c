"""Map point properties derived from its observations (ORB-SLAM sec. III-C): mean viewing direction,
scale-invariance distances, representative descriptor, and the pyramid level predicted at a distance."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.pipeline.matching import hamming_matrix


def update_normal_and_depth(point: MapPoint, keyframes: dict[int, KeyFrame]) -> None:
    """Recompute ``normal_w`` (mean unit vector from the observing cameras to the point) and the distance
    range [d_min, d_max] in which ORB can detect it, from its reference keyframe's pyramid level:
    d_max = d_ref * scale^level, d_min = d_max / scale^(n_levels - 1) (ORB-SLAM MapPoint::UpdateNormalAndDepth).
    """
    if not point.observations:
        return
    normals = []
    for kf_id in point.observations:
        kf = keyframes.get(kf_id)
        if kf is None:
            continue
        v = point.xyz_w - kf.center_w
        n = np.linalg.norm(v)
        if n > 0:
            normals.append(v / n)
    if normals:
        mean = np.mean(normals, axis=0)
        norm = np.linalg.norm(mean)
        point.normal_w = mean / norm if norm > 0 else mean
    ref = keyframes.get(point.ref_kf_id)
    if ref is None or point.ref_kf_id not in point.observations:
        return
    feats = ref.features
    level = int(feats.level[point.observations[point.ref_kf_id]])
    dist = float(np.linalg.norm(point.xyz_w - ref.center_w))
    point.d_max_m = dist * feats.scale_factor**level
    point.d_min_m = point.d_max_m / feats.scale_factor ** (feats.n_levels - 1)


def compute_distinctive_descriptor(point: MapPoint, keyframes: dict[int, KeyFrame]) -> None:
    """Choose as the point's descriptor the observation with the least median Hamming distance to all the
    others (ORB-SLAM MapPoint::ComputeDistinctiveDescriptors). Deterministic: ties go to the lowest keyframe id."""
    descs = []
    for kf_id in sorted(point.observations):
        kf = keyframes.get(kf_id)
        if kf is not None:
            descs.append(kf.features.descriptors[point.observations[kf_id]])
    if not descs:
        return
    if len(descs) == 1:
        point.descriptor = descs[0].copy()
        return
    d = np.stack(descs)
    dist = hamming_matrix(d, d)
    median = np.median(dist, axis=1)
    point.descriptor = d[int(np.argmin(median))].copy()


def predict_level(
    d_max_m: NDArray[np.float64] | float,
    distance_m: NDArray[np.float64] | float,
    scale_factor: float,
    n_levels: int,
) -> NDArray[np.int64]:
    """Pyramid level at which a point at ``distance_m`` should be detected, given its d_max
    (ORB-SLAM MapPoint::PredictScale): ceil(log(d_max / d) / log(scale)), clipped to [0, n_levels - 1]."""
    ratio = np.asarray(d_max_m, np.float64) / np.maximum(np.asarray(distance_m, np.float64), 1e-12)
    level = np.ceil(np.log(np.maximum(ratio, 1e-12)) / np.log(scale_factor)).astype(np.int64)
    return np.asarray(np.clip(level, 0, n_levels - 1))
