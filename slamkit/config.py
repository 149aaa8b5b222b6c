"""Composing slamkit's Hydra config, with or without the CLI.

``conf/`` ships inside the package as ``slamkit.conf``, so composition works from any working directory
after a plain (non-editable) install. Plugin-provided config nodes are stored in Hydra's ConfigStore
before composing, so ``<kind>=<name>`` reaches every installed plugin's components.
"""

from __future__ import annotations

from collections.abc import Sequence

from omegaconf import DictConfig

from slamkit.plugins import ComponentRegistry

CONFIG_MODULE = "slamkit.conf"
CONFIG_NAME = "config"
CONFIG_SEARCH_PATH = "pkg://" + CONFIG_MODULE


def prepare_registry(registry: ComponentRegistry | None = None) -> ComponentRegistry:
    """Discover plugins (unless given a registry) and register their config nodes with Hydra."""
    registry = registry or ComponentRegistry.discover()
    registry.register_config_nodes()
    return registry


def compose_config(
    overrides: Sequence[str] = (),
    registry: ComponentRegistry | None = None,
    config_name: str = CONFIG_NAME,
) -> DictConfig:
    """Compose the run config as ``slamkit run OVERRIDES...`` would, without the CLI (tests, notebooks)."""
    from hydra import compose, initialize_config_module

    prepare_registry(registry)
    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))
