"""Reading a Hydra multirun directory: one ``JobResult`` per job of the sweep, finished or not.

A job directory is any folder under the multirun directory holding ``.hydra/overrides.yaml`` (Hydra writes it
when the job starts) or ``metrics.json`` (the job writes it when it ends, also when it fails). The jobs the sweep
will run are expanded from ``multirun.yaml`` as Hydra's basic sweeper does, so jobs that have not started yet
show as ``pending``: a report of a sweep still running is complete in its rows.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from slamkit.errors import ConfigError

MULTIRUN_FILE = "multirun.yaml"
OVERRIDES_FILE = Path(".hydra") / "overrides.yaml"
METRICS_FILE = "metrics.json"

#: Job states: finished (``ok``), finished with an error (``failed``), started without metrics.json yet
#: (``incomplete``: running, or killed), not started (``pending``), metrics.json that is not JSON (``unreadable``).
STATUSES = ("ok", "failed", "incomplete", "pending", "unreadable")


@dataclass(frozen=True)
class JobResult:
    """One job of a sweep: its overrides (``key -> value`` as typed on the command line), state and metrics."""

    overrides: dict[str, str]
    status: str
    metrics: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    job_dir: Path | None = None


@dataclass(frozen=True)
class Sweep:
    """Every job of a multirun directory (started or pending), in the sweep's job order where known."""

    root: Path
    jobs: list[JobResult]

    def varying_keys(self, exclude: tuple[str, ...] = ()) -> list[str]:
        """Override keys whose value differs between jobs (the swept values), in first-seen order."""
        keys: list[str] = []
        for job in self.jobs:
            keys.extend(k for k in job.overrides if k not in keys and k not in exclude)
        return [k for k in keys if len({job.overrides.get(k) for job in self.jobs}) > 1]


def override_key(override: str) -> tuple[str, str]:
    """``"+a.b=3"`` -> ``("a.b", "3")``: the key without Hydra's ``+``/``++``/``~`` prefix, and the value."""
    key, sep, value = override.partition("=")
    if not sep:
        raise ConfigError(f"override {override!r} is not KEY=VALUE")
    return key.lstrip("+~"), value


def parse_overrides(lines: list[str]) -> dict[str, str]:
    """The overrides of one job as a ``key -> value`` dict (see ``override_key``)."""
    return dict(override_key(str(line)) for line in lines)


def _read_yaml_list(path: Path) -> list[str]:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the job's overrides ({exc})") from exc
    if data is None:
        return []
    if not isinstance(data, list):
        raise ConfigError(f"{path}: expected a YAML list of KEY=VALUE overrides, got {type(data).__name__}")
    return [str(x) for x in data]


def load_job(job_dir: Path) -> JobResult:
    """Read one job directory: overrides from ``.hydra/overrides.yaml``, state and metrics from metrics.json."""
    overrides_path = job_dir / OVERRIDES_FILE
    overrides = parse_overrides(_read_yaml_list(overrides_path)) if overrides_path.is_file() else {}
    metrics_path = job_dir / METRICS_FILE
    if not metrics_path.is_file():
        return JobResult(overrides, "incomplete", job_dir=job_dir)
    try:
        metrics = json.loads(metrics_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:  # e.g. being written right now
        return JobResult(overrides, "unreadable", error=f"{metrics_path}: {exc}", job_dir=job_dir)
    if not isinstance(metrics, dict):
        return JobResult(overrides, "unreadable", error=f"{metrics_path}: not a JSON object", job_dir=job_dir)
    status = str(metrics.get("status", "ok"))
    error = metrics.get("error")
    if status != "ok" and error is None:
        error = f"status {status!r} without an error message"
    return JobResult(overrides, "ok" if status == "ok" else "failed", metrics, error, job_dir)


def expected_jobs(multirun_yaml: Path) -> list[dict[str, str]] | None:
    """The overrides of every job the sweep launches, expanded from multirun.yaml as Hydra's basic sweeper does
    (the sweeper's ``params``, then the command line's overrides, which win); None when that cannot be done
    (another sweeper, or no multirun.yaml)."""
    if not multirun_yaml.is_file():
        return None
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    try:
        cfg = OmegaConf.to_container(OmegaConf.load(multirun_yaml), resolve=False)  # ${now:} stays as written
        hydra_node: dict[str, Any] = (cfg.get("hydra") if isinstance(cfg, dict) else None) or {}
        sweeper = hydra_node.get("sweeper") or {}
        if "BasicSweeper" not in str(sweeper.get("_target_", "")):
            return None
        params = sweeper.get("params") or {}
        lines = [f"{k}={v}" for k, v in params.items()]
        lines += [str(x) for x in (hydra_node.get("overrides") or {}).get("task") or []]
        parsed = OverridesParser.create().parse_overrides(lines)
        batches = BasicSweeper.split_arguments(parsed, None)
    except Exception as exc:  # a hand-edited or foreign multirun.yaml: report what was run
        raise ConfigError(f"{multirun_yaml}: cannot expand the sweep's jobs ({exc})") from exc
    return [parse_overrides(list(job)) for batch in batches for job in batch]


def _job_dirs(root: Path) -> list[Path]:
    found = {p.parent.parent for p in root.rglob(str(OVERRIDES_FILE))}
    found |= {p.parent for p in root.rglob(METRICS_FILE)}
    return sorted(found, key=lambda p: [int(s) if s.isdigit() else s for s in p.relative_to(root).parts])


def collect_sweep(root: Path) -> Sweep:
    """Every job of the multirun directory ``root``: the ones that ran or run (from their directories) and,
    when multirun.yaml can be expanded, the ones not started yet (``pending``)."""
    if not root.is_dir():
        raise ConfigError(f"{root}: no such multirun directory (expected Hydra's sweep dir, multirun/DATE/TIME)")
    started = [load_job(d) for d in _job_dirs(root)]
    expected = expected_jobs(root / MULTIRUN_FILE)
    if not started and not expected:
        raise ConfigError(
            f"{root}: no job found (no {MULTIRUN_FILE}, no */{OVERRIDES_FILE.as_posix()} or */{METRICS_FILE})"
        )
    if expected is None:
        return Sweep(root, started)
    jobs: list[JobResult] = []
    remaining = list(started)
    for overrides in expected:
        match = next((j for j in remaining if j.overrides == overrides), None)
        if match is None:
            jobs.append(JobResult(overrides, "pending"))
        else:
            remaining.remove(match)
            jobs.append(match)
    return Sweep(root, jobs + remaining)  # jobs the expansion did not predict are still reported
