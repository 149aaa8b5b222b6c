"""Monocular ORB-SLAM on the KITTI 07 slice of ../shared/datasets (160 frames, 1241x376, 2000 features).

The bar (issue 4): at least 97% of all frames tracked and ATE RMSE (Sim3, all tracked frames) under 0.5% of the
path length. ORB-SLAM3's own C++ tracked 156 of 160 with 0.28-0.34 m on the same frames.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.run_metrics import runner_metrics


@pytest.mark.slow
@pytest.mark.shared_data
def test_kitti07_slice_tracks_97_percent_with_ate_under_half_percent(shared_datasets: Path) -> None:
    cfg = compose_config(
        [
            "+experiment=kitti07",
            f"dataset.root={shared_datasets / 'kitti'}",
            "runner=sequential",
            "runner.progress=false",
        ]
    )
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    metrics = runner_metrics(runner, dataset)
    assert metrics["frames"] == 160
    assert metrics["frames_tracked"] >= 0.97 * metrics["frames"]
    assert 85.0 < metrics["path_length_m"] < 95.0
    assert metrics["ate_rmse_pct_of_path"] < 0.5
