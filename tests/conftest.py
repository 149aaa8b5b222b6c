"""Shared pytest fixtures."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slamkit.map.point_table import SYNCED_ATTRIBUTES

REPO_ROOT = Path(__file__).resolve().parents[1]
TEST_PLUGINS_DIR = REPO_ROOT / "tests" / "plugins"


def pip_install_into(target: Path, *sources: Path) -> Path:
    """pip-install the distributions at ``sources`` (folders with a pyproject) into ``target`` without their
    dependencies or build isolation: a real install, as a user's or a third party's would be. Returns target."""
    for source in sources:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "install",
                "--quiet",
                "--no-deps",
                "--no-build-isolation",
                "--target",
                str(target),
                str(source),
            ],
            check=True,
        )
    return target


@pytest.fixture(scope="session")
def pip_install() -> Callable[..., Path]:
    """``pip_install(target, *sources)``: see pip_install_into."""
    return pip_install_into


@contextmanager
def _plugins_installed(target: Path, *distributions: str) -> Iterator[Path]:
    """pip-install the example plugin distributions ``tests/plugins/<name>`` into ``target`` and put ``target`` on
    sys.path for the duration of the block."""
    pip_install_into(target, *(TEST_PLUGINS_DIR / dist for dist in distributions))
    sys.path.insert(0, str(target))
    try:
        yield target
    finally:
        sys.path.remove(str(target))


def shared_datasets_dir() -> Path | None:
    """../shared/datasets beside the checkout (or $SLAMKIT_SHARED_DATASETS), if present."""
    env = os.environ.get("SLAMKIT_SHARED_DATASETS")
    path = Path(env) if env else REPO_ROOT.parent / "shared" / "datasets"
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared_datasets() -> Path:
    """Path to the real datasets in ../shared/datasets; skips the test when they are not beside the checkout."""
    path = shared_datasets_dir()
    if path is None:
        pytest.skip("../shared/datasets is not beside this checkout (real-data test skipped)")
    return path


def _assert_point_table_matches_points(store: Any) -> None:
    """Every point in the map reads back from the store's point table exactly as from the object."""
    ids = np.array(store.point_ids(), np.int64)
    assert ids.size > 0
    for name, _, _ in SYNCED_ATTRIBUTES:
        from_objects = np.array([getattr(store.get_point(int(p)), name) for p in ids])
        np.testing.assert_array_equal(store.point_rows(ids, name), from_objects, err_msg=name)


@pytest.fixture
def assert_point_table_matches_points() -> Callable[[Any], None]:
    """assert_point_table_matches_points(store): the point table tracking gathers from equals the points."""
    return _assert_point_table_matches_points


def _assert_no_culled_keyframe_alive(runner: Any) -> None:
    """After a run, the only KeyFrame objects alive are those in the Atlas's maps (and in local mapping's queue, empty
    at the end): the run log and the trajectory recorder keep ids and poses, not the culled keyframes themselves
    (their features and bag of words, about 0.3 MB each, would make memory grow per keyframe ever made)."""
    import gc

    from slamkit.map.entities import KeyFrame

    gc.collect()
    alive = {id(o): o for o in gc.get_objects() if isinstance(o, KeyFrame)}
    in_maps = {
        id(store.get_keyframe(k))
        for m in runner.atlas.map_ids()
        for store in [runner.atlas.get(m)]
        for k in store.keyframe_ids()
    }
    assert len(runner.log.mapping) > len(in_maps), "the run culled no keyframe: nothing to check"
    assert set(alive) == in_maps, f"{len(alive) - len(in_maps)} keyframes alive outside the maps"


@pytest.fixture
def assert_no_culled_keyframe_alive() -> Callable[[Any], None]:
    """assert_no_culled_keyframe_alive(runner): keyframes culled during the run were freed."""
    return _assert_no_culled_keyframe_alive


@pytest.fixture(scope="module")
def dictmap_plugin(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The example third-party MapStore (tests/plugins/slamkit_dictmap, ``map=dict``), pip-installed into a private
    folder on sys.path for the module's tests."""
    with _plugins_installed(tmp_path_factory.mktemp("site"), "slamkit_dictmap") as site:
        yield site
