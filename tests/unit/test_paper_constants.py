"""Each ORB-SLAM constant the issues name is a config value with the paper's default, and overriding it
reaches the typed config the code reads (tests/unit/test_config_keys_read.py checks that code reads every key)."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from slamkit.config import compose_config
from slamkit.pipeline.config import (
    Chi2Config,
    LocalMappingConfig,
    LoopClosingConfig,
    MatcherConfig,
    PipelineConfig,
    TrackingConfig,
)
from slamkit.plugins import ComponentRegistry

# (config key, paper default, where it comes from)
PIPELINE_CONSTANTS = [
    ("pipeline.loop_closing.theta_min", 100, "III-D essential graph"),
    ("pipeline.local_mapping.keyframe_culling_redundancy", 0.9, "VI-E"),
    ("pipeline.local_mapping.keyframe_culling_min_observers", 3, "VI-E"),
    ("pipeline.local_mapping.point_min_found_ratio", 0.25, "VI-B"),
    ("pipeline.local_mapping.point_min_observations", 3, "VI-B"),
    ("pipeline.local_mapping.ba_iterations_first", 5, "appendix: local BA"),
    ("pipeline.local_mapping.ba_iterations_second", 10, "appendix: local BA"),
    ("pipeline.tracking.local_map_min_view_cos", 0.5, "V-D: cos 60 deg"),
    ("pipeline.tracking.keyframe_max_frames", 0, "code: NeedNewKeyFrame mMaxFrames = Camera.fps (0: dataset fps)"),
    ("pipeline.tracking.keyframe_min_tracked_points", 15, "code: NeedNewKeyFrame c2 mnMatchesInliers > 15"),
    ("pipeline.tracking.keyframe_max_ref_ratio", 0.9, "code: NeedNewKeyFrame c2 thRefRatio monocular"),
    ("pipeline.tracking.pose_rounds", 4, "appendix: motion-only BA"),
    ("pipeline.tracking.local_map_neighbors_per_keyframe", 10, "code: UpdateLocalKeyFrames best 10 covisibles"),
    ("pipeline.tracking.local_map_wide_search_frames_after_reloc", 2, "code: SearchLocalPoints th=5"),
    ("pipeline.tracking.keyframe_ref_min_observations", 3, "code: NeedNewKeyFrame nMinObs"),
    ("pipeline.tracking.keyframe_ref_min_observations_small_map", 2, "code: NeedNewKeyFrame nMinObs"),
    ("pipeline.tracking.reloc_min_bow_matches", 15, "code: Relocalization, V-C"),
    ("pipeline.tracking.reloc_pnp_ransac_iterations", 300, "code: Relocalization PnPsolver"),
    ("pipeline.tracking.reloc_pnp_ransac_confidence", 0.99, "code: Relocalization PnPsolver"),
    ("pipeline.tracking.reloc_min_pnp_inliers", 10, "code: Relocalization PnPsolver"),
    ("pipeline.tracking.reloc_search_radius_px", 10.0, "code: Relocalization SearchByProjection"),
    ("pipeline.tracking.reloc_search_max_distance", 100, "code: Relocalization SearchByProjection"),
    ("pipeline.tracking.reloc_search_radius_fine_px", 3.0, "code: Relocalization SearchByProjection"),
    ("pipeline.tracking.reloc_search_max_distance_fine", 64, "code: Relocalization SearchByProjection"),
    ("pipeline.tracking.reset_lost_map_max_keyframes", 10, "ORB-SLAM3 code: Track, KeyFramesInMap() <= 10"),
    ("pipeline.tracking.time_recently_lost_s", 3.0, "ORB-SLAM3 code: Track, visual-only 3.0 s"),
    ("pipeline.loop_closing.consistency_detections", 3, "VII-A"),
    ("pipeline.loop_closing.candidate_min_covisible_weight", 30, "VII-A"),
    ("pipeline.loop_closing.min_keyframes_between_loops", 10, "code: DetectLoop"),
    ("pipeline.loop_closing.sim3_min_bow_matches", 20, "code: ComputeSim3"),
    ("pipeline.loop_closing.loop_search_radius_px", 10.0, "code: ComputeSim3 SearchByProjection"),
    ("pipeline.loop_closing.loop_fuse_radius_px", 4.0, "code: SearchAndFuse"),
    ("pipeline.matcher.th_low", 50, "code: ORBmatcher::TH_LOW"),
    ("pipeline.matcher.th_high", 100, "code: ORBmatcher::TH_HIGH"),
    ("pipeline.matcher.rotation_bins", 30, "code: ORBmatcher::HISTO_LENGTH"),
    ("pipeline.matcher.epipole_min_dist2", 100.0, "code: SearchForTriangulation"),
    ("pipeline.matcher.ratio_initialization", 0.9, "code: MonocularInitialization ORBmatcher(0.9, true)"),
    ("pipeline.matcher.ratio_reference_kf", 0.7, "code: TrackReferenceKeyFrame ORBmatcher(0.7, true)"),
    ("pipeline.matcher.ratio_local_map", 0.8, "code: SearchLocalPoints ORBmatcher(0.8)"),
    ("pipeline.matcher.ratio_relocalization", 0.75, "code: Relocalization ORBmatcher(0.75, true)"),
    ("pipeline.matcher.ratio_loop", 0.75, "code: ComputeSim3 ORBmatcher(0.75, true)"),
    ("pipeline.chi2.mono", 5.991, "appendix: chi-square 95%, 2 dof"),
    ("pipeline.chi2.stereo", 7.815, "appendix: chi-square 95%, 3 dof"),
    ("pipeline.chi2.epipolar", 3.84, "code: CheckDistEpipolarLine"),
    ("pipeline.chi2.fuse_mono", 5.99, "code: ORBmatcher::Fuse"),
    ("pipeline.chi2.sim3", 10.0, "code: OptimizeSim3 th2"),
    ("pipeline.chi2.sim3_ransac", 9.21, "code: Sim3Solver"),
]
#: Sections every step of the pipeline shares (each step's config carries them as ``cfg.matcher``, ``cfg.chi2``).
SHARED_SECTIONS = ("matcher", "chi2")
COMPONENT_CONSTANTS = [
    ("map", "covisibility_min_shared", 15, "III-D covisibility graph"),
    ("initializer", "T_H", 5.991, "IV"),
    ("initializer", "T_F", 3.841, "IV"),
    ("initializer", "gamma", 5.991, "IV: Gamma = T_H"),
    ("initializer", "rh_threshold", 0.45, "ORB-SLAM paper IV-3 (ORB-SLAM3 code: 0.50)"),
    ("initializer", "min_parallax_deg", 1.0, "code"),
    ("features", "n_features", 1000, "VIII: 640x480"),
    ("features", "scale_factor", 1.2, "III-A"),
    ("features", "n_levels", 8, "III-A"),
    ("features", "ini_fast_threshold", 20, "code iniThFAST"),
    ("features", "min_fast_threshold", 7, "code minThFAST"),
]


@pytest.mark.parametrize(("key", "default", "source"), PIPELINE_CONSTANTS)
def test_pipeline_constant_is_configurable(key: str, default: float, source: str) -> None:
    assert OmegaConf.select(compose_config(), key) == default, f"{key} should default to {default} ({source})"
    new = default * 2 if isinstance(default, int) else round(default / 2, 4)
    cfg = compose_config([f"{key}={new}"])
    typed = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline))  # type: ignore[arg-type]
    section, name = key.split(".")[1:]
    assert getattr(getattr(typed, section), name) == new
    if section in SHARED_SECTIONS:  # the one value reaches tracking, local mapping and loop closing alike
        for step in (typed.tracking, typed.local_mapping, typed.loop_closing):
            assert getattr(getattr(step, section), name) == new


def test_config_dataclass_defaults_are_the_yaml_defaults() -> None:
    """The typed config's defaults (used by code built without Hydra, e.g. tests) do not drift from the YAML."""
    from_yaml = PipelineConfig.from_node(OmegaConf.to_container(compose_config().pipeline))  # type: ignore[arg-type]
    assert from_yaml.tracking == TrackingConfig()
    assert from_yaml.local_mapping == LocalMappingConfig()
    assert from_yaml.loop_closing == LoopClosingConfig()
    assert (from_yaml.matcher, from_yaml.chi2) == (MatcherConfig(), Chi2Config())


@pytest.mark.parametrize(("group", "name", "default", "source"), COMPONENT_CONSTANTS)
def test_component_constant_is_configurable(group: str, name: str, default: float, source: str) -> None:
    registry = ComponentRegistry.discover()
    assert compose_config()[group][name] == default, f"{group}.{name} should default to {default} ({source})"
    new = default + 1 if isinstance(default, int) else round(default * 0.9, 4)
    built = registry.instantiate(group, compose_config([f"{group}.{name}={new}"])[group])
    assert getattr(built, name) == new


def test_kitti_experiment_uses_2000_features() -> None:
    assert compose_config(["+experiment=kitti07"]).features.n_features == 2000
