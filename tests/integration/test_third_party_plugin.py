"""A real third-party plugin distribution, pip-installed by the test, is discovered and selected by config;
deliberately broken plugins give errors naming the plugin and what is wrong."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamkit.config import compose_config
from slamkit.errors import PluginError
from slamkit.interfaces import FeatureExtractor
from slamkit.plugins import ComponentRegistry

PLUGINS_DIR = Path(__file__).resolve().parents[1] / "plugins"


@pytest.fixture(scope="module")
def installed_plugins(tmp_path_factory: pytest.TempPathFactory, pip_install: Callable[..., Path]) -> Iterator[Path]:
    """pip-installs the example distributions into a private folder and puts it on sys.path."""
    target = pip_install(tmp_path_factory.mktemp("site"), PLUGINS_DIR / "slamkit_gftt", PLUGINS_DIR / "slamkit_broken")
    sys.path.insert(0, str(target))
    try:
        yield target
    finally:
        sys.path.remove(str(target))


@pytest.fixture(scope="module")
def registry(installed_plugins: Path) -> ComponentRegistry:
    return ComponentRegistry.discover()


def textured_image(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((480, 640), 128, np.uint8)
    for _ in range(300):
        x, y = (int(v) for v in rng.integers(0, [640, 480]))
        cv2.circle(img, (x, y), int(rng.integers(3, 25)), int(rng.integers(0, 256)), -1)
    return img


def test_third_party_component_is_discovered_with_its_distribution(registry: ComponentRegistry) -> None:
    comp = registry.get("features", "gftt_orb")
    assert comp.distribution == "slamkit-gftt-example 0.1.0"
    assert comp.plugin == "gftt"
    assert comp.spec.target == "slamkit_gftt.extractor.GfttOrbExtractor"
    # the built-in components are still there beside it
    assert registry.get("features", "opencv_orb").distribution.startswith("slamkit ")


def test_config_override_selects_the_third_party_extractor(registry: ComponentRegistry) -> None:
    cfg = compose_config(["features=gftt_orb", "features.n_features=300"], registry=registry)
    assert cfg.features._target_ == "slamkit_gftt.extractor.GfttOrbExtractor"
    extractor = registry.instantiate("features", cfg.features)
    assert isinstance(extractor, FeatureExtractor)
    feats = extractor.extract(textured_image())
    assert 200 <= len(feats) <= 300  # the override reached the component
    assert feats.descriptors.shape == (len(feats), 32)
    assert np.all(feats.level == 0)


def test_broken_plugins_are_reported_by_name_and_reason(registry: ComponentRegistry) -> None:
    reasons = {f.plugin: f.reason for f in registry.failures}
    assert "slamkit_dependency_that_does_not_exist" in reasons["broken_import"]
    assert reasons["broken_import"].startswith("failed to import 'slamkit_broken.import_error'")
    assert "implements no slamkit hook" in reasons["broken_no_hook"]
    assert all(f.distribution == "slamkit-broken-example 0.1.0" for f in registry.failures)


def test_component_of_the_wrong_protocol_is_rejected_when_built(registry: ComponentRegistry) -> None:
    cfg = compose_config(["features=not_an_extractor"], registry=registry)
    with pytest.raises(PluginError) as err:
        registry.instantiate("features", cfg.features)
    msg = str(err.value)
    assert "plugin 'broken_protocol'" in msg and "slamkit-broken-example" in msg
    assert "does not implement FeatureExtractor" in msg and "extract" in msg


def test_missing_component_error_lists_alternatives_and_broken_plugins(registry: ComponentRegistry) -> None:
    with pytest.raises(PluginError) as err:
        registry.get("features", "sift")
    msg = str(err.value)
    assert "features=sift" in msg and "gftt_orb" in msg and "broken_import" in msg


def test_slamkit_plugins_command_lists_third_party_and_failures(installed_plugins: Path) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(installed_plugins), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(
        [sys.executable, "-m", "slamkit", "plugins", "--json"], env=env, capture_output=True, text=True, check=True
    ).stdout
    listing = json.loads(out)
    rows = {(c["kind"], c["name"]): c for c in listing["components"]}
    assert rows[("features", "gftt_orb")]["distribution"] == "slamkit-gftt-example 0.1.0"
    assert {f["plugin"] for f in listing["failures"]} == {"broken_import", "broken_no_hook"}
    strict = subprocess.run(
        [sys.executable, "-m", "slamkit", "plugins", "--strict"], env=env, capture_output=True, text=True
    )
    assert strict.returncode == 1
    assert "plugins that failed to load" in strict.stdout
