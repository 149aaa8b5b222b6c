"""build_optimizer: the configured optimizer, inline or in a worker process (``optimizer.worker``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from slamkit.errors import ConfigError
from slamkit.interfaces import Optimizer
from slamkit.plugins import ComponentRegistry

__all__ = ["WORKER_MODES", "build_optimizer"]

WORKER_MODES = ("inline", "process")


def _plain(node: Mapping[str, Any]) -> dict[str, Any]:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(node, DictConfig):
            container = OmegaConf.to_container(node, resolve=True)
            return {str(k): v for k, v in container.items()} if isinstance(container, dict) else {}
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    return dict(node)


def build_optimizer(node: Mapping[str, Any], registry: ComponentRegistry | None = None) -> Optimizer:
    """Build the optimizer described by the composed ``optimizer`` config node.

    node: has ``_target_`` and the backend's settings, plus optionally ``worker``: "inline" (default) builds the
    backend here through ``registry``; "process" starts a ProcessOptimizer whose worker builds it. The returned
    object implements slamkit.interfaces.Optimizer either way; a ProcessOptimizer should be closed (close() or a
    with block) when no longer needed (an atexit hook closes it otherwise).
    """
    config = _plain(node)
    worker = config.pop("worker", "inline")
    if worker not in WORKER_MODES:
        raise ConfigError(f"optimizer.worker = {worker!r}: expected one of {', '.join(WORKER_MODES)}")
    if worker == "process":
        from slamkit.optim.worker import ProcessOptimizer

        return ProcessOptimizer(config)
    reg = registry if registry is not None else ComponentRegistry.discover()
    optimizer: Optimizer = reg.instantiate("optimizer", config)
    return optimizer
