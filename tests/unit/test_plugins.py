"""The plugin manager on in-process plugin objects: registration, failures, protocol checks."""

from __future__ import annotations

import types

import pytest

from slamkit.errors import PluginError
from slamkit.hookspecs import ComponentSpec, hookimpl
from slamkit.plugins import ComponentRegistry


def plugin_module(name: str, specs: object) -> types.ModuleType:
    mod = types.ModuleType(name)

    @hookimpl
    def slamkit_components() -> object:
        return specs

    mod.slamkit_components = slamkit_components  # type: ignore[attr-defined]
    return mod


def test_builtin_components_are_registered_through_entry_points() -> None:
    registry = ComponentRegistry.discover()
    keys = {c.key for c in registry.components()}
    assert {
        "dataset=synthetic",
        "dataset=tum_rgbd",
        "dataset=euroc",
        "dataset=kitti",
        "dataset=folder",
        "dataset=video",
        "features=opencv_orb",
    } <= keys
    assert registry.get("features", "opencv_orb").plugin == "orb"


def test_duplicate_component_is_refused_naming_both_plugins() -> None:
    registry = ComponentRegistry()
    spec = ComponentSpec("features", "x", "a.B", {})
    registry.add_plugin("first", plugin_module("first", [spec]), "dist-a 1.0")
    registry.add_plugin("second", plugin_module("second", [spec]), "dist-b 2.0")
    assert registry.get("features", "x").plugin == "first"
    (failure,) = registry.failures
    assert failure.plugin == "second" and "already provided by plugin 'first' (dist-a 1.0)" in failure.reason


def test_unknown_kind_and_bad_return_value_are_failures() -> None:
    registry = ComponentRegistry()
    registry.add_plugin("odd", plugin_module("odd", [ComponentSpec("teleporter", "x", "a.B")]))
    registry.add_plugin("bad", plugin_module("bad", "not a list"))
    reasons = {f.plugin: f.reason for f in registry.failures}
    assert "unknown kind 'teleporter'" in reasons["odd"]
    assert "expected list[ComponentSpec]" in reasons["bad"]


def test_misspelled_hook_is_a_validation_failure() -> None:
    mod = types.ModuleType("typo")

    @hookimpl
    def slamkit_component() -> list[ComponentSpec]:  # missing the final "s"
        return []

    mod.slamkit_component = slamkit_component  # type: ignore[attr-defined]
    registry = ComponentRegistry()
    registry.add_plugin("typo", mod)
    (failure,) = registry.failures
    assert failure.plugin == "typo" and "invalid hook implementation" in failure.reason


def test_unimportable_target_names_the_plugin() -> None:
    registry = ComponentRegistry()
    registry.add_plugin(
        "ghost", plugin_module("ghost", [ComponentSpec("features", "g", "no_such_pkg.Extractor")]), "ghost-dist 0.1"
    )
    with pytest.raises(PluginError, match=r"features=g from plugin 'ghost' \(ghost-dist 0.1\) could not be built"):
        registry.instantiate("features", {"_target_": "no_such_pkg.Extractor"})
