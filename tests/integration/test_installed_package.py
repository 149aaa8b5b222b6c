"""After a plain (non-editable) install, `slamkit run` finds its configs from any working directory."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def plain_install(tmp_path_factory: pytest.TempPathFactory, pip_install: Callable[..., Path]) -> Path:
    return pip_install(tmp_path_factory.mktemp("plain_install"), REPO_ROOT)


def run_installed(target: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(target), "PYTHONSAFEPATH": "1"}
    return subprocess.run([sys.executable, "-m", "slamkit", *args], cwd=cwd, env=env, capture_output=True, text=True)


def test_plain_install_ships_configs_and_plugins(plain_install: Path, tmp_path: Path) -> None:
    assert (plain_install / "slamkit" / "conf" / "config.yaml").is_file()
    assert (plain_install / "slamkit" / "conf" / "pipeline" / "orbslam.yaml").is_file()
    assert (plain_install / "slamkit_orb" / "plugin.py").is_file()
    probe = subprocess.run(
        [sys.executable, "-c", "import slamkit.conf, slamkit_orb; print(slamkit.conf.__file__, slamkit_orb.__file__)"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(plain_install), "PYTHONSAFEPATH": "1"},
        capture_output=True,
        text=True,
        check=True,
    )
    assert all(p.startswith(str(plain_install)) for p in probe.stdout.split())


def test_slamkit_run_composes_from_any_directory(plain_install: Path, tmp_path: Path) -> None:
    result = run_installed(plain_install, tmp_path, "run", "--cfg", "job", "dataset.scene=long_loop")
    assert result.returncode == 0, result.stderr
    assert "scene: long_loop" in result.stdout
    assert "theta_min: 100" in result.stdout


def test_slamkit_plugins_lists_builtin_components(plain_install: Path, tmp_path: Path) -> None:
    result = run_installed(plain_install, tmp_path, "plugins")
    assert result.returncode == 0, result.stderr
    for name in ("synthetic", "tum_rgbd", "euroc", "kitti", "folder", "video", "opencv_orb"):
        assert f" {name} " in result.stdout


def test_building_the_wheel_warns_of_nothing_and_ships_every_data_file(tmp_path: Path) -> None:
    """Issue 18 item 6: setuptools used to warn about every config and vocabulary folder it had to guess at
    ("Package 'slamkit.conf.dataset' is absent from the `packages` configuration"); the wheel must ship every
    config, vocabulary and py.typed marker the repository tracks."""
    import zipfile

    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-v", "-w", str(tmp_path), "."],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    noise = ("byte-compiling is disabled", "is neither a file nor a directory")  # this machine's pip set-up
    warnings = [
        line
        for line in (built.stdout + built.stderr).splitlines()
        if "warning" in line.lower() and not any(n in line for n in noise)
    ]
    assert warnings == []
    (wheel,) = tmp_path.glob("slamkit-*.whl")
    shipped = set(zipfile.ZipFile(wheel).namelist())
    tracked = subprocess.run(
        ["git", "ls-files", "conf", "plugins", "slamkit"], cwd=REPO_ROOT, capture_output=True, text=True
    ).stdout.split()
    if not tracked:
        pytest.skip("not a git checkout: the tracked data files cannot be listed")
    for path in tracked:
        if not path.endswith((".yaml", ".skvoc", "py.typed")):
            continue
        installed = path.replace("conf/", "slamkit/conf/", 1) if path.startswith("conf/") else path
        installed = installed.removeprefix("plugins/")
        assert installed in shipped, f"{path} is not in the wheel"
