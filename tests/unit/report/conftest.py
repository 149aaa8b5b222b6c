"""Fixtures for the sweep-report tests: multirun directories laid out as Hydra and ``slamkit run`` write them
(``multirun.yaml`` composed by Hydra itself, ``N/.hydra/overrides.yaml``, ``N/metrics.json``)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest
import yaml

WriteJob = Callable[..., Path]
WriteMultirun = Callable[[Path, Sequence[str]], Path]


def write_job(root: Path, num: int, overrides: Sequence[str], metrics: dict[str, Any] | str | None) -> Path:
    """Job directory ``root/num`` with its overrides; metrics as a dict (JSON), raw text, or None (no file)."""
    job = root / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(list(overrides)))
    if isinstance(metrics, dict):
        (job / "metrics.json").write_text(json.dumps(metrics))
    elif isinstance(metrics, str):
        (job / "metrics.json").write_text(metrics)
    return job


def write_multirun_yaml(root: Path, overrides: Sequence[str]) -> Path:
    """``root/multirun.yaml`` as Hydra saves it for ``slamkit run -m OVERRIDES``: the composed config with its
    ``hydra`` node (sweeper params from the selected sweep config, the command line in hydra.overrides.task)."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from slamkit.config import CONFIG_MODULE, CONFIG_NAME, prepare_registry

    prepare_registry()
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        cfg = compose(config_name=CONFIG_NAME, overrides=list(overrides), return_hydra_config=True)
    root.mkdir(parents=True, exist_ok=True)
    path = root / "multirun.yaml"
    OmegaConf.save(cfg, path)
    return path


@pytest.fixture
def job_writer() -> WriteJob:
    return write_job


@pytest.fixture
def multirun_writer() -> WriteMultirun:
    return write_multirun_yaml


def ok_metrics(seed: int, **values: Any) -> dict[str, Any]:
    """A finished job's metrics.json with the given values."""
    return {"status": "ok", "seed": seed, **values}
