"""Configs compose without the CLI, with the overrides a user types."""

from __future__ import annotations

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from slamkit.config import compose_config


def test_default_config_selects_the_synthetic_dataset_and_paper_constants() -> None:
    cfg = compose_config()
    assert cfg.dataset._target_ == "slamkit.io.synthetic.dataset.SyntheticDataset"
    assert cfg.dataset.seed == cfg.seed == 0  # the top-level seed drives the synthetic world
    assert cfg.pipeline.loop_closing.theta_min == 100  # ORB-SLAM III-D
    assert cfg.map.covisibility_min_shared == 15  # ORB-SLAM III-D
    assert cfg.pipeline.local_mapping.keyframe_culling_redundancy == 0.9  # ORB-SLAM VI-E
    assert cfg.runner.kind == "threaded"  # issue 6: ORB-SLAM's three threads by default
    assert compose_config(["+sweep=theta_min"]).runner.kind == "sequential"  # ablations are reproducible


def test_group_and_value_overrides() -> None:
    cfg = compose_config(["dataset=kitti", "dataset.root=/data/kitti", "dataset.sequence='05'", "seed=7"])
    assert cfg.dataset._target_.endswith("KittiDataset")
    assert cfg.dataset.root == "/data/kitti" and cfg.dataset.sequence == "05"
    assert cfg.seed == 7


def test_experiment_config_sets_the_scene() -> None:
    cfg = compose_config(["+experiment=long_loop"])
    assert cfg.dataset.scene == "long_loop"


def test_sweep_config_declares_the_theta_min_values() -> None:
    from hydra import compose, initialize_config_module

    from slamkit.config import CONFIG_MODULE, prepare_registry

    prepare_registry()
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        cfg = compose(config_name="config", overrides=["+sweep=theta_min"], return_hydra_config=True)
    assert OmegaConf.select(cfg, "hydra.sweeper.params")["pipeline.loop_closing.theta_min"] == "15,50,100,200"


@pytest.mark.parametrize("backend", ["gtsam", "scipy"])
def test_plus_backend_selects_the_optimizer(backend: str) -> None:
    default = compose_config()
    cfg = compose_config([f"+backend={backend}"])
    assert cfg.optimizer._target_.startswith(f"slamkit_{backend}.")
    # the rest of the config is untouched
    assert OmegaConf.to_container(cfg.pipeline) == OmegaConf.to_container(default.pipeline)
    assert compose_config([f"optimizer={backend}"]).optimizer == cfg.optimizer


def test_unknown_option_is_a_composition_error_listing_the_options() -> None:
    with pytest.raises(ConfigCompositionException) as err:
        compose_config(["features=sift"])
    assert "opencv_orb" in str(err.value.__cause__ or err.value) and "orb" in str(err.value.__cause__ or err.value)
