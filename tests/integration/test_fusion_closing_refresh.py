"""Local mapping's fusion (LocalMapper._search_in_neighbors) on real maps (the synthetic room, monocular and RGB-D,
sequential runner): its closing refresh recomputes only the new keyframe's points whose observations changed since
insertion refreshed them (LocalMapper._changed_points), and refreshing the points it leaves out rewrites none of their
bits; the keyframe's points it fuses pass after pass (fusion.KeyFramePoints, rows re-gathered only where a merge
changed the point) are the ids and rows a fresh gather from the map gives at every pass."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.map.entities import KeyFrame
from slamkit.pipeline import fusion, local_mapping
from slamkit.pipeline.map_points import refresh_points

ATTRIBUTES = ("normal_w", "d_min_m", "d_max_m", "descriptor")


@pytest.mark.parametrize(
    "overrides", [["dataset.max_frames=70"], ["frontend=rgbd", "dataset.max_frames=30"]], ids=["mono", "rgbd"]
)
def test_points_the_closing_refresh_leaves_out_hold_what_a_refresh_would_write(
    monkeypatch: pytest.MonkeyPatch, overrides: list[str]
) -> None:
    changed_points = local_mapping.LocalMapper._changed_points
    counts = {"observed": 0, "left_out": 0}

    def checked(mapper: local_mapping.LocalMapper, kf: KeyFrame) -> np.ndarray:
        changed = changed_points(mapper, kf)
        store = mapper.store
        ids = np.unique(kf.point_ids[kf.point_ids >= 0])
        ids = ids[store.has_points(ids)]
        left_out = np.setdiff1d(ids, changed)
        counts["observed"] += int(ids.size)
        counts["left_out"] += int(left_out.size)
        if left_out.size:
            before = {a: store.point_rows(left_out, a) for a in ATTRIBUTES}
            refresh_points(store, left_out.tolist())  # the old closing refresh of these points
            for a in ATTRIBUTES:
                after = store.point_rows(left_out, a)
                assert np.array_equal(before[a].view(np.uint8), after.view(np.uint8)), a  # bit for bit
        return changed

    monkeypatch.setattr(local_mapping.LocalMapper, "_changed_points", checked)
    cfg = compose_config(["runner=sequential", "runner.progress=false", "optimizer.worker=inline", *overrides])
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    # the path is exercised: most points are left out (fusion changes the observations of a minority)
    assert counts["observed"] > 1000
    assert counts["left_out"] > counts["observed"] // 4


@pytest.mark.parametrize(
    "overrides", [["dataset.max_frames=70"], ["frontend=rgbd", "dataset.max_frames=30"]], ids=["mono", "rgbd"]
)
def test_the_keyframe_points_held_across_fusion_passes_equal_a_fresh_gather(
    monkeypatch: pytest.MonkeyPatch, overrides: list[str]
) -> None:
    fuse_points = local_mapping.fuse_points
    passes = {"held": 0, "regathered": 0, "rows": 0}
    update = fusion.KeyFramePoints.update

    def counted_update(held: fusion.KeyFramePoints, store: object) -> fusion.KeyFramePoints:
        before = held._at.copy()
        out = update(held, store)  # type: ignore[arg-type]
        passes["regathered"] += int((held._at != before).sum())
        return out

    def checked(store, kf, point_ids, *args, **kwargs):  # type: ignore[no-untyped-def]
        if isinstance(point_ids, fusion.KeyFramePoints):
            passes["held"] += 1
            passes["rows"] += int(point_ids.ids.size)
            pids = point_ids.kf.point_ids
            ids = pids[pids >= 0]
            ids = ids[store.has_points(ids)]
            np.testing.assert_array_equal(point_ids.ids, ids)
            for name in ("xyz_w", "normal_w", "d_min_m", "d_max_m"):
                fresh = store.point_rows(ids, name)
                held = getattr(point_ids, name)
                assert held.dtype == fresh.dtype and held.shape == fresh.shape, name
                assert np.array_equal(held.view(np.uint8), fresh.view(np.uint8)), name  # bit for bit
        return fuse_points(store, kf, point_ids, *args, **kwargs)

    monkeypatch.setattr(local_mapping, "fuse_points", checked)
    monkeypatch.setattr(fusion.KeyFramePoints, "update", counted_update)
    cfg = compose_config(["runner=sequential", "runner.progress=false", "optimizer.worker=inline", *overrides])
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    assert passes["held"] >= 3
    # the rows held save gathers: some rows the passes read were gathered in an earlier pass (mono 70 frames: most)
    assert 0 < passes["regathered"] < passes["rows"]
