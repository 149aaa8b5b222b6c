"""Typed views of the ``pipeline`` config group (conf/pipeline/orbslam.yaml documents each value and where
it comes from in the paper). Unknown or missing keys are errors naming the key."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from slamkit.errors import ConfigError

T = TypeVar("T")


def from_mapping(cls: type[T], node: Mapping[str, Any], prefix: str) -> T:
    """Build a config dataclass from a mapping; ConfigError names unknown/missing keys as ``prefix.key``."""
    # fields marked ``shared`` (the matcher and chi-square sections) are filled by PipelineConfig, not from node
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("shared")}  # type: ignore[arg-type]
    unknown = sorted(set(node) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + '.' + k for k in unknown)}; "
            f"expected some of: {', '.join(sorted(fields))}"
        )
    missing = [n for n, f in fields.items() if n not in node and f.default is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"missing config key(s) {', '.join(prefix + '.' + k for k in missing)}")
    values = {}
    for name, value in node.items():
        default = fields[name].default
        if isinstance(default, bool) and not isinstance(value, bool):
            raise ConfigError(f"{prefix}.{name}: expected true or false, got {value!r}")
        if isinstance(default, int | float) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"{prefix}.{name}: expected a number, got {value!r}")
            if value < 0:
                raise ConfigError(f"{prefix}.{name}: expected a non-negative number, got {value!r}")
            value = type(default)(value)
        values[name] = value
    return cls(**values)


@dataclass(frozen=True)
class MatcherConfig:
    """ORB-SLAM's ORBmatcher constants (``pipeline.matcher``): Hamming thresholds (bits), the rotation histogram,
    and the nearest/second-nearest ratio of each kind of search."""

    th_low: int = 50
    th_high: int = 100
    rotation_bins: int = 30
    epipole_min_dist2: float = 100.0
    ratio_initialization: float = 0.9
    ratio_reference_kf: float = 0.7
    ratio_local_map: float = 0.8
    ratio_relocalization: float = 0.75
    ratio_loop: float = 0.75


@dataclass(frozen=True)
class Chi2Config:
    """The chi-square gates (``pipeline.chi2``): squared reprojection errors over the level's sigma^2 above them
    are outliers."""

    mono: float = 5.991
    stereo: float = 7.815
    epipolar: float = 3.84
    fuse_mono: float = 5.99
    sim3: float = 10.0
    sim3_ransac: float = 9.21
    stereo_rounded: float = 7.8


@dataclass(frozen=True)
class TrackingConfig:
    pose_optimization: str = "compiled"
    motion_model_search_radius_px: float = 15.0
    min_motion_model_matches: int = 20
    min_reference_kf_matches: int = 15
    min_inliers_after_pose_opt: int = 10
    local_map_min_view_cos: float = 0.5
    local_map_search_radius_px: float = 1.0
    local_map_search_radius_relocalized_px: float = 5.0
    local_map_search_radius_rgbd_px: float = 3.0
    right_coordinate_gate: bool = False
    motion_model_search_radius_stereo_px: float = 7.0
    local_map_covisible_keyframes: int = 80
    local_map_neighbors_per_keyframe: int = 10
    local_map_wide_search_frames_after_reloc: int = 2
    min_local_map_inliers: int = 30
    min_local_map_inliers_after_reloc: int = 50
    keyframe_max_frames: int = 0
    keyframe_min_tracked_points: int = 15
    keyframe_max_ref_ratio: float = 0.9
    keyframe_ref_min_observations: int = 3
    keyframe_ref_min_observations_small_map: int = 2
    keyframe_max_ref_ratio_stereo: float = 0.75
    keyframe_max_ref_ratio_stereo_single: float = 0.4
    keyframe_c1c_ref_ratio_stereo: float = 0.25
    keyframe_close_tracked_max: int = 100
    keyframe_close_untracked_min: int = 70
    reloc_min_bow_matches: int = 15
    reloc_pnp_ransac_iterations: int = 300
    reloc_pnp_ransac_confidence: float = 0.99
    reloc_min_pnp_inliers: int = 10
    reloc_pnp_min_set: int = 4
    reloc_pnp_epsilon: float = 0.5
    reloc_pnp_iterations_per_turn: int = 5
    reloc_fine_search_min_inliers: int = 30
    reloc_search_radius_px: float = 10.0
    reloc_search_max_distance: int = 100
    reloc_search_radius_fine_px: float = 3.0
    reloc_search_max_distance_fine: int = 64
    init_feature_factor: float = 2.0
    init_extractor_after_init: bool = False
    init_min_features: int = 100
    stereo_init_min_features: int = 500
    init_min_matches: int = 100
    init_search_radius_px: float = 100.0
    init_min_map_points: int = 50
    init_ba_iterations: int = 20
    pose_rounds: int = 4
    pose_iterations_per_round: int = 10
    reset_lost_map_max_keyframes: int = 10
    time_recently_lost_s: float = 3.0
    localization_min_motion_model_inliers: int = 21
    # the shared sections pipeline.matcher and pipeline.chi2 (set by PipelineConfig.from_node)
    matcher: MatcherConfig = field(default_factory=MatcherConfig, metadata={"shared": True})
    chi2: Chi2Config = field(default_factory=Chi2Config, metadata={"shared": True})


@dataclass(frozen=True)
class LocalMappingConfig:
    point_min_found_ratio: float = 0.25
    point_min_observations: int = 3
    point_culling_window_kfs: int = 3
    point_culling_max_observations_stereo: int = 3
    triangulation_neighbors: int = 20
    triangulation_neighbors_stereo: int = 10
    min_parallax_cos: float = 0.9998
    scale_consistency_factor: float = 1.5
    fuse_neighbors: int = 20
    fuse_neighbors_stereo: int = 10
    fuse_second_neighbors: int = 5
    fuse_search_radius_px: float = 3.0
    local_ba: bool = True
    keyframe_culling: bool = True
    keyframe_culling_redundancy: float = 0.9
    point_bad_max_observations: int = 2
    keyframe_culling_min_observers: int = 3
    keyframe_culling_max_candidates: int = 101
    keyframe_culling_max_candidates_aborted: int = 21
    min_baseline_depth_ratio: float = 0.01
    stereo_new_points_min: int = 100
    ba_iterations_first: int = 5
    ba_iterations_second: int = 10
    ba_update_normal_and_depth: bool = False
    ba_point_bad_max_observations: int = 1
    new_map_points_culled: bool = True
    new_map_points_culled_stereo: bool = False
    fuse_right_coordinate_gate: bool = False
    # the shared sections pipeline.matcher and pipeline.chi2 (set by PipelineConfig.from_node)
    matcher: MatcherConfig = field(default_factory=MatcherConfig, metadata={"shared": True})
    chi2: Chi2Config = field(default_factory=Chi2Config, metadata={"shared": True})


@dataclass(frozen=True)
class LoopClosingConfig:
    enabled: bool = True
    theta_min: int = 100
    candidate_min_covisible_weight: int = 30
    consistency_detections: int = 3
    sim3_ransac_min_inliers: int = 20
    sim3_ransac_max_iterations: int = 300
    sim3_ransac_probability: float = 0.99
    min_inliers_after_sim3_opt: int = 20
    min_loop_matches: int = 40
    global_ba: bool = True
    global_ba_iterations: int = 10
    geometric_verification: bool = True
    verify_covisible_keyframes: int = 5
    verify_coincidences: int = 3
    verify_search_radius_px: float = 3.0
    verify_min_matches: int = 30
    verify_max_misses: int = 2
    max_loop_rotation_deg: float = 20.0
    min_keyframes_between_loops: int = 10
    sim3_min_bow_matches: int = 20
    loop_search_radius_px: float = 10.0
    loop_fuse_radius_px: float = 4.0
    n_best_candidates: int = 3
    candidate_covisibles: int = 5
    bow_ratio: float = 0.9
    common_regions_ransac_min_inliers: int = 15
    common_regions_search_radius_px: float = 8.0
    common_regions_hamming_ratio: float = 1.5
    common_regions_min_projected: int = 50
    common_regions_refined_radius_px: float = 5.0
    common_regions_min_refined: int = 80
    confirm_min_optimized: int = 50
    confirm_min_matches: int = 100
    merge_maps: bool = True
    merge_window_keyframes: int = 15
    merge_window_max_tries: int = 3
    merge_ba_iterations_first: int = 5
    merge_ba_iterations_second: int = 10
    merge_essential_graph: bool = True
    merge_global_ba: bool = False
    # the shared sections pipeline.matcher and pipeline.chi2 (set by PipelineConfig.from_node)
    matcher: MatcherConfig = field(default_factory=MatcherConfig, metadata={"shared": True})
    chi2: Chi2Config = field(default_factory=Chi2Config, metadata={"shared": True})


@dataclass(frozen=True)
class PipelineConfig:
    tracking: TrackingConfig
    local_mapping: LocalMappingConfig
    loop_closing: LoopClosingConfig
    matcher: MatcherConfig
    chi2: Chi2Config

    @staticmethod
    def from_node(node: Mapping[str, Any]) -> PipelineConfig:
        """node: the composed ``pipeline`` group (a plain mapping). The matcher and chi-square sections are read
        once and given to each step's config (``cfg.matcher``, ``cfg.chi2``)."""
        unknown = sorted(set(node) - {"tracking", "local_mapping", "loop_closing", "matcher", "chi2"})
        if unknown:
            raise ConfigError(f"unknown config section(s) {', '.join('pipeline.' + k for k in unknown)}")
        matcher = from_mapping(MatcherConfig, node.get("matcher", {}), "pipeline.matcher")
        chi2 = from_mapping(Chi2Config, node.get("chi2", {}), "pipeline.chi2")
        tracking = from_mapping(TrackingConfig, node.get("tracking", {}), "pipeline.tracking")
        local_mapping = from_mapping(LocalMappingConfig, node.get("local_mapping", {}), "pipeline.local_mapping")
        loop_closing = from_mapping(LoopClosingConfig, node.get("loop_closing", {}), "pipeline.loop_closing")
        return PipelineConfig(
            dataclasses.replace(tracking, matcher=matcher, chi2=chi2),
            dataclasses.replace(local_mapping, matcher=matcher, chi2=chi2),
            dataclasses.replace(loop_closing, matcher=matcher, chi2=chi2),
            matcher,
            chi2,
        )
