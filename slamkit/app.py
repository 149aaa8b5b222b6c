"""The job behind ``slamkit run``: build the configured components and the runner, and run SLAM on the dataset.

The run directory (trajectory.tum, keyframes.tum, metrics.json, config.yaml, frames.csv, loops.json,
trajectory.png) is written by the built-in outputs plugin on the lifecycle hooks (slamkit/eval/outputs.py); the
metrics are computed in slamkit/eval/run_metrics.py."""

from __future__ import annotations

import json
import logging
import re
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from slamkit.errors import ConfigError
from slamkit.eval.outputs import PLUGIN_NAME as OUTPUTS_PLUGIN
from slamkit.interfaces import Dataset, Optimizer
from slamkit.map import mapfile_run
from slamkit.pipeline.config import PipelineConfig
from slamkit.pipeline.keyframe_pins import KeyFramePins
from slamkit.pipeline.local_mapping import LocalMapper
from slamkit.pipeline.loop_closing import LoopCloser
from slamkit.pipeline.tracking import Tracker
from slamkit.plugins import ComponentRegistry
from slamkit.problems import PoseOnlyProblem, PoseOnlyResult
from slamkit.runtime.events import EventDispatcher
from slamkit.runtime.sequential import SequentialRunner
from slamkit.runtime.source import CAMERA_BUFFER_FRAMES, frame_count
from slamkit.runtime.threaded import ThreadedRunner

log = logging.getLogger("slamkit")

RUNNER_KINDS = ("sequential", "threaded")
#: ``mode``: mapping (ORB-SLAM's default) or localization only in a loaded map (ORB-SLAM ActivateLocalizationMode)
MODES = ("slam", "localization")
Runner = SequentialRunner | ThreadedRunner


#: ``${oc.select:dataset.orb_extractor.FIELD,DEFAULT}``: a ``features.*`` value the dataset's camera settings decide
_FROM_DATASET = re.compile(r"^\$\{oc\.select:dataset\.orb_extractor\.(\w+),[^}]*\}$")


def build_components(cfg: DictConfig, registry: ComponentRegistry) -> dict[str, Any]:
    """Instantiate every configured component group through the registry (checked against its interface).

    The dataset comes first: its depth is read only when the front end uses it (``resolve_dataset_depth``), and
    its camera's ORB-SLAM extractor settings fill the ``features.*`` keys the command line did not set
    (``camera_feature_settings``), written back into ``cfg`` so the run's config.yaml shows what was used."""
    built: dict[str, Any] = {}
    from slamkit.optim.factory import build_optimizer

    # the maps (``map``) are built by the Atlas, each with the Atlas's id allocator (build_runner)
    for kind in ("dataset", "features", "place", "initializer", "optimizer"):
        node = cfg.get(kind)
        if node is None or "_target_" not in node:
            continue
        if kind == "dataset":
            resolve_frontend(cfg)
            resolve_dataset_depth(cfg)
        if kind == "features" and "dataset" in built:
            camera_feature_settings(node, built["dataset"])
        # the optimizer may run in a worker process (optimizer.worker=process): the factory decides
        built[kind] = build_optimizer(node, registry) if kind == "optimizer" else registry.instantiate(kind, node)
    return built


#: The monocular front end's target: the one a stereo dataset replaces (resolve_frontend).
_MONOCULAR_FRONTEND = "slamkit.frontend.mono.MonocularFrontEnd"


def resolve_frontend(cfg: DictConfig) -> None:
    """The dataset's natural front end (issue 16 item 5): a dataset reading stereo pairs (``dataset.stereo: true``)
    with the monocular front end runs ``frontend=stereo`` (conf/frontend/stereo.yaml), logged; written into ``cfg`` so
    the run's config.yaml shows it. Any other front end is kept (``frontend=rgbd``, a third-party one). Depth maps
    select nothing: a TUM RGB-D run stays monocular, reading every colour frame, unless ``frontend=rgbd`` is given
    (docs/pipeline.md)."""
    dataset, frontend = cfg.get("dataset"), cfg.get("frontend")
    if dataset is None or frontend is None or dataset.get("stereo") is not True:
        return
    if str(frontend.get("_target_")) != _MONOCULAR_FRONTEND:
        return
    from importlib.resources import files

    from slamkit.config import CONFIG_MODULE

    node = OmegaConf.create(files(CONFIG_MODULE).joinpath("frontend", "stereo.yaml").read_text())
    with read_write(cfg), open_dict(cfg):
        cfg.frontend = node
    log.info("dataset.stereo=true: running frontend=stereo (the dataset reads stereo pairs)")


def resolve_dataset_depth(cfg: DictConfig) -> None:
    """``dataset.use_depth: null`` -> whether the configured front end uses depth maps (its class attribute
    ``uses_depth``, False when absent): a monocular run reads every colour frame, with no depth association."""
    node = cfg.get("dataset")
    if node is None or "use_depth" not in node or node.get("use_depth") is not None:
        return
    frontend = cfg.get("frontend")
    uses_depth = False
    if frontend is not None and "_target_" in frontend:
        from hydra.utils import get_class

        uses_depth = bool(getattr(get_class(str(frontend._target_)), "uses_depth", False))
    with read_write(node):
        node.use_depth = uses_depth


def camera_feature_settings(features: DictConfig, dataset: Dataset) -> dict[str, Any]:
    """Give the dataset's ORB-SLAM extractor settings (``orb_settings``: its settings file's ``ORBextractor.*``, else
    its config's ``dataset.orb_extractor``) to the ``features.*`` keys that still hold their default, the
    interpolation ``${oc.select:dataset.orb_extractor.FIELD,DEFAULT}``; a key set on the command line (or by an
    experiment) is not an interpolation any more and wins. Assigns in place; returns {key: value} it set."""
    orb = dataset.orb_settings if hasattr(dataset, "orb_settings") else None  # optional (SequenceDataset has it)
    assigned: dict[str, Any] = {}
    for key in list(features.keys()):
        if not OmegaConf.is_interpolation(features, str(key)):
            continue
        raw = OmegaConf.to_container(features, resolve=False)
        assert isinstance(raw, dict)
        match = _FROM_DATASET.match(str(raw[key]))
        if match is None:
            continue
        if orb is not None and hasattr(orb, match.group(1)):
            assigned[str(key)] = getattr(orb, match.group(1))
        else:  # the default of the interpolation (the extractor's, ORB-SLAM's paper values)
            assigned[str(key)] = features[key]
    with read_write(features):
        for key, value in assigned.items():
            features[key] = value
    if orb is not None and assigned:
        log.info("features from the dataset's ORB-SLAM settings: %s", assigned)
    return assigned


def _output_dir() -> Path:
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def build_runner(cfg: DictConfig, registry: ComponentRegistry | None = None) -> tuple[Runner, Dataset]:
    """Build the dataset, the components and the runner a composed config describes (no Hydra runtime
    needed: tests and notebooks call this with ``slamkit.config.compose_config(...)``)."""
    localization = run_mode(cfg) == "localization"  # checked before anything is built
    registry = registry or ComponentRegistry.discover()
    for failure in registry.failures:
        log.warning("%s", failure)
    components = build_components(cfg, registry)
    dataset: Dataset = components["dataset"]
    pipeline = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline, resolve=True))  # type: ignore[arg-type]
    rng = np.random.default_rng(int(cfg.seed))
    place = components.get("place")  # None: no relocalization, no loop closing
    if localization and place is None:
        raise ConfigError(
            "mode=localization starts by relocalizing in the loaded map: it needs a place recognizer (place=dbow)"
        )
    map_node = cfg.get("map")
    if map_node is None or "_target_" not in map_node:
        raise ConfigError("map: missing; expected a map store (map=memory)")
    # every map of the Atlas is a store of the configured kind sharing the Atlas's ids; one keyframe database;
    # map.load=FILE: the Atlas saved there (slamkit/map/mapfile_run.py), tracking then starts by relocalizing in it
    store_node = mapfile_run.store_node(map_node)
    atlas = mapfile_run.run_atlas(
        map_node,
        lambda ids: registry.instantiate("map", store_node, ids=ids),
        place,
        [c for c in (dataset.camera, getattr(dataset, "camera_right", None)) if c is not None],
    )
    if localization and atlas.active.n_keyframes() == 0:
        raise ConfigError(
            f"mode=localization: the active map of map.load={map_node.get('load')} has no keyframe to localize against"
        )
    if localization:
        # a localization run's trajectory is its own pass, not a session of the map (docs/atlas.md, "Multi-session")
        atlas.loaded_frames = {}
    init_extractor = None
    factor = pipeline.tracking.init_feature_factor
    if factor != 1 and "n_features" in cfg.features:
        node = {str(k): v for k, v in cfg.features.items()}
        node["n_features"] = round(int(node["n_features"]) * factor)
        init_extractor = registry.instantiate("features", node)
    frontend_node = cfg.get("frontend")
    if frontend_node is None or "_target_" not in frontend_node:
        raise ConfigError("frontend: missing; expected a front end (frontend=mono)")
    frontend = registry.instantiate(
        "frontend", frontend_node, extractor=components["features"], init_extractor=init_extractor
    )
    if hasattr(frontend, "bind_dataset"):  # optional: a front end taking calibration from the dataset (stereo bf)
        frontend.bind_dataset(dataset)
    tracker = Tracker(
        pipeline.tracking,
        frontend,
        components["initializer"],
        components["optimizer"],
        atlas,
        rng,
        place,
        pose_optimizer=_pose_optimizer(pipeline.tracking.pose_optimization, components["optimizer"]),
        fps=float(dataset.fps),
        localization_only=localization,
        session_start=mapfile_run.session_start(map_node),
    )
    kind = str(cfg.runner.get("kind", "sequential"))
    if kind not in RUNNER_KINDS:
        raise ConfigError(f"runner.kind = {kind!r}: expected one of {', '.join(RUNNER_KINDS)}")
    background_optimizer = components["optimizer"]
    if kind == "threaded":
        background_optimizer = _background_optimizer(cfg, components["optimizer"])
    pins = KeyFramePins()  # loop closing pins the keyframes it uses, local mapping's culling leaves them
    # localization only: no local mapping and no loop closing (ORB-SLAM ActivateLocalizationMode stops local mapping,
    # and loop closing gets its keyframes from it)
    mapper = None if localization else LocalMapper(pipeline.local_mapping, atlas, background_optimizer, place, pins)
    loop_closer = None
    if place is not None and not localization:
        loop_closer = LoopCloser(pipeline.loop_closing, atlas, background_optimizer, place, rng, pins)
    progress = bool(cfg.runner.get("progress", True))
    bad_frames = str(cfg.runner.get("bad_frames", "skip"))  # checked by the runner
    events = EventDispatcher(registry.hook, critical={OUTPUTS_PLUGIN})
    runner: Runner
    new_map_ms = cfg.runner.get("modelled_mapping_new_map_ms", None)  # null: runner.modelled_mapping_ms
    modelled_ms = float(cfg.runner.get("modelled_mapping_ms", 0.0))
    if kind == "threaded":
        runner = ThreadedRunner(
            tracker,
            mapper,
            atlas,
            progress=progress,
            loop_closer=loop_closer,
            realtime=bool(cfg.runner.get("realtime", False)),
            speed=float(cfg.runner.get("speed", 1.0)),
            preload=bool(cfg.runner.get("preload", False)),
            background_niceness=_int_setting(cfg.runner, "background_niceness", 0, 19, 0),
            gil_switch_interval_s=_switch_interval_s(cfg.runner),
            events=events,
            bad_frames=bad_frames,
            modelled_mapping_ms=modelled_ms,
            modelled_mapping_new_map_ms=None if new_map_ms is None else float(new_map_ms),
            wait_for_local_mapping=bool(cfg.runner.get("wait_for_local_mapping", True)),
            frame_waits_for=str(cfg.runner.get("frame_waits_for", "local_mapping")),
            extract_ahead=_int_setting(cfg.runner, "extract_ahead", 0, 64, 0),
            realtime_extract_ahead=bool(cfg.runner.get("realtime_extract_ahead", False)),
            extract_ahead_single_threaded=bool(cfg.runner.get("extract_ahead_single_threaded", False)),
            realtime_extract_single_threaded=bool(cfg.runner.get("realtime_extract_single_threaded", True)),
            realtime_extract_ahead_init=bool(cfg.runner.get("realtime_extract_ahead_init", False)),
            realtime_camera_buffer=_int_setting(cfg.runner, "realtime_camera_buffer", 1, 64, CAMERA_BUFFER_FRAMES),
        )
    else:
        runner = SequentialRunner(
            tracker,
            mapper,
            atlas,
            progress=progress,
            loop_closer=loop_closer,
            events=events,
            bad_frames=bad_frames,
            record_reference=str(cfg.runner.get("record_reference", "tracked")),
            modelled_mapping_ms=modelled_ms,
            modelled_mapping_new_map_ms=None if new_map_ms is None else float(new_map_ms),
        )
    return runner, dataset


def run_mode(cfg: DictConfig) -> str:
    """``mode`` of a run config, checked: "slam" (default) or "localization", which needs ``map.load`` and refuses
    ``map.save`` (ConfigError: a one-line error, exit 2 from the CLI).

    Localization only (ORB-SLAM2/3 System::ActivateLocalizationMode) tracks in a map and changes none of it. ORB-SLAM3
    would still write its Atlas at shutdown when asked to (System::Shutdown saves whatever the mode); slamkit refuses
    ``map.save`` with it instead: the map has nothing new to save, and ``map.save`` naming the loaded file would
    rewrite the file this mode promises to leave untouched."""
    mode = cfg.get("mode", "slam")
    if mode not in MODES:
        raise ConfigError(f"mode = {mode!r}: expected one of {', '.join(MODES)}")
    if mode == "localization":
        map_node = cfg.get("map") or {}
        if map_node.get("load") in (None, "", False):
            raise ConfigError("mode=localization needs a map to localize in: map.load=FILE (a map saved with map.save)")
        if map_node.get("save") not in (None, "", False):
            raise ConfigError(
                "mode=localization leaves the map as it was: map.save is not allowed with it (save from a mode=slam run)"
            )
    return str(mode)


def _int_setting(node: DictConfig, key: str, low: int, high: int, default: int) -> int:
    value = node.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"runner.{key} = {value!r}: expected an integer in [{low}, {high}]")
    return int(value)


def _switch_interval_s(node: DictConfig) -> float | None:
    """runner.gil_switch_interval_ms (null: keep the interpreter's) -> seconds."""
    value = node.get("gil_switch_interval_ms", None)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value <= 100:
        raise ConfigError(f"runner.gil_switch_interval_ms = {value!r}: expected a number in (0, 100] ms or null")
    return float(value) / 1e3


def _pose_optimizer(choice: str, optimizer: Optimizer) -> Callable[[PoseOnlyProblem], PoseOnlyResult] | None:
    """Tracking's motion-only BA: None = the tracker's compiled default, or the optimizer backend's."""
    if choice == "compiled":
        return None
    if choice == "optimizer":
        return optimizer.optimize_pose
    raise ConfigError(f"pipeline.tracking.pose_optimization = {choice!r}: expected 'compiled' or 'optimizer'")


def _background_optimizer(cfg: DictConfig, optimizer: Optimizer) -> Optimizer:
    """The optimizer local mapping and loop closing use in the threaded runner: a backend that holds the GIL
    through its C++ calls (GTSAM) would freeze tracking during a local BA, so it runs in a worker process
    (``runner.offload_gil_holding_optimizer``, default true); others run inline."""
    if not getattr(optimizer, "holds_gil", False) or not bool(cfg.runner.get("offload_gil_holding_optimizer", True)):
        return optimizer
    if str(cfg.optimizer.get("worker", "inline")) == "process":
        return optimizer
    from slamkit.optim.factory import build_optimizer

    node = OmegaConf.to_container(cfg.optimizer, resolve=True)
    assert isinstance(node, dict)
    node["worker"] = "process"
    log.info("optimizer %s holds the GIL: local mapping and loop closing use it in a worker process", optimizer.name)
    return build_optimizer({str(k): v for k, v in node.items()})


def _is_multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


def write_failed_job(out_dir: Path, cfg: DictConfig, error: str, stage: str) -> dict[str, Any]:
    """metrics.json of a job that failed before it had anything to measure (``stage``: where it failed)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics: dict[str, Any] = {"status": "failed", "stage": stage, "error": error, "seed": cfg.get("seed")}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str) + "\n")
    try:
        (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    except Exception:  # an unresolvable config may be the very failure: keep it unresolved
        (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    return metrics


def _written_metrics(out_dir: Path) -> dict[str, Any]:
    """The metrics.json the outputs plugin wrote."""
    metrics: dict[str, Any] = json.loads((out_dir / "metrics.json").read_text())
    return metrics


def run_job(cfg: DictConfig) -> dict[str, Any]:
    """Hydra task function of ``slamkit run``: ``System(cfg).run_dataset()`` of the Python API (slamkit/api.py)
    writing into Hydra's output directory. A failing job writes metrics.json with ``status: failed`` and
    ``error``; in a multirun it then returns (logged as an error) so the other jobs of the sweep go on, in a
    single run it raises."""
    from slamkit.api import System  # the Python API; this job is its user (slamkit.api imports this module)

    out_dir = _output_dir()
    try:
        system = System(cfg, output_dir=out_dir)
    except Exception as exc:
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        metrics = write_failed_job(out_dir, cfg, error, "build")
        if not _is_multirun():
            raise
        log.error("job failed while building its components: %s", error)
        return metrics
    dataset = system.dataset
    n_frames = frame_count(dataset)
    log.info("dataset %s: %s frames -> %s", getattr(dataset, "name", "?"), n_frames or "live, unknown", out_dir)
    start = time.perf_counter()
    try:
        # the outputs plugin writes the run directory when the run finishes, also when it fails; map.save=FILE
        # writes the Atlas then too (slamkit/map/mapfile_run.py)
        with mapfile_run.saving_map(cfg.map, system.atlas, out_dir, system.config, system.runner.map_frames):
            system.run_dataset()
    except BaseException as exc:
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        if not isinstance(exc, Exception) or not _is_multirun():
            raise
        log.error("job failed while running: %s", error)
        if not (out_dir / "metrics.json").is_file():  # the outputs plugin itself failed
            return write_failed_job(out_dir, cfg, error, "outputs")
        return _written_metrics(out_dir)
    metrics = _written_metrics(out_dir)
    log.info(
        "done in %.1f s: %s",
        time.perf_counter() - start,
        json.dumps(
            {k: metrics.get(k) for k in ("frames_tracked", "keyframes", "map_points", "ate_rmse_m", "kf_ate_rmse_m")}
        ),
    )
    print(f"results in {out_dir}")
    return metrics
