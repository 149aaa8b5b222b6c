"""Issue 16 item 5: the dataset selecting its natural front end. A dataset reading stereo pairs
(``dataset.stereo=true``) runs ``frontend=stereo`` without it being named; every other choice is kept, and depth maps
select nothing (a TUM RGB-D run stays monocular unless ``frontend=rgbd`` is given: issue 14 reads every colour
frame)."""

from __future__ import annotations

import pytest

from slamkit.app import resolve_dataset_depth, resolve_frontend
from slamkit.config import compose_config


@pytest.mark.parametrize(
    ("overrides", "target"),
    [
        (["dataset.stereo=true"], "slamkit.frontend.stereo.StereoFrontEnd"),
        (["dataset=kitti", "dataset.stereo=true"], "slamkit.frontend.stereo.StereoFrontEnd"),
        (["dataset=kitti"], "slamkit.frontend.mono.MonocularFrontEnd"),
        (["dataset.stereo=true", "frontend=rgbd"], "slamkit.frontend.rgbd.RgbdFrontEnd"),
    ],
)
def test_a_stereo_dataset_selects_the_stereo_front_end(overrides: list[str], target: str) -> None:
    cfg = compose_config(overrides)
    resolve_frontend(cfg)
    assert cfg.frontend._target_ == target


def test_the_selected_stereo_node_is_the_one_frontend_stereo_composes() -> None:
    """The node put in place is conf/frontend/stereo.yaml as `frontend=stereo` composes it (ThDepth 35, ...)."""
    chosen = compose_config(["dataset.stereo=true"])
    resolve_frontend(chosen)
    named = compose_config(["frontend=stereo", "dataset.stereo=true"])
    assert dict(chosen.frontend) == dict(named.frontend)


def test_tum_depth_is_read_only_for_the_rgbd_front_end() -> None:
    """dataset=tum_rgbd leaves use_depth null: monocular reads no depth (every colour frame kept); frontend=rgbd
    reads it."""
    for overrides, expected in ((["dataset=tum_rgbd"], False), (["dataset=tum_rgbd", "frontend=rgbd"], True)):
        cfg = compose_config(overrides)
        resolve_frontend(cfg)
        resolve_dataset_depth(cfg)
        assert cfg.dataset.use_depth is expected
