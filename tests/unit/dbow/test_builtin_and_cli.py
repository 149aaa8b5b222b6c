"""The built-in vocabulary (shipped, or trained on first use and cached), ``place=dbow`` through the
plugin registry, and the ``vocab`` command line."""

from __future__ import annotations

from pathlib import Path

import pytest
from slamkit_dbow import builtin
from slamkit_dbow.builtin import BUILTIN_RECIPE, Recipe, load_builtin_vocabulary, shipped_vocabulary_path
from slamkit_dbow.cli import main
from slamkit_dbow.files import load_vocabulary
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.errors import ConfigError
from slamkit.interfaces import PlaceRecognizer
from slamkit.plugins import ComponentRegistry

TINY = Recipe(synthetic=("planar:1000:3",), k=4, L=2)


def test_shipped_vocabulary_is_present_and_recorded() -> None:
    path = shipped_vocabulary_path()
    assert path.is_file(), f"{path} is missing: run {BUILTIN_RECIPE.command(str(path))}"
    vocab = load_vocabulary(path)
    assert (vocab.k, vocab.L, vocab.n_words) == (10, 4, 10_000)
    assert vocab.metadata["recipe"] == BUILTIN_RECIPE.as_dict()
    assert vocab.metadata["n_images"] == 480 and path.stat().st_size < 1_000_000


def test_fresh_machine_trains_on_first_use_and_caches(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No shipped file, empty cache: the vocabulary is trained, cached under $XDG_CACHE_HOME/slamkit, and
    the next load reads the cache instead of training."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    missing = tmp_path / "not-shipped.skvoc"
    first = load_builtin_vocabulary(TINY, shipped=missing, progress=False)
    cached = builtin.cached_vocabulary_path(TINY)
    assert cached.is_file() and cached.is_relative_to(tmp_path / "cache" / "slamkit")
    assert (first.k, first.L) == (4, 2) and first.n_words > 4

    def no_training(*args: object, **kwargs: object) -> None:
        raise AssertionError("the cached vocabulary should have been used")

    monkeypatch.setattr(builtin, "train_recipe", no_training)
    assert load_builtin_vocabulary(TINY, shipped=missing).same_as(first)


def test_place_dbow_through_the_registry() -> None:
    registry = ComponentRegistry.discover()
    comp = registry.get("place", "dbow")
    assert comp.spec.target == "slamkit_dbow.recognizer.DbowPlaceRecognizer"
    recognizer = registry.instantiate("place", comp.config_node())
    assert isinstance(recognizer, PlaceRecognizer) and isinstance(recognizer, DbowPlaceRecognizer)
    assert recognizer.vocabulary.n_words == 10_000
    with pytest.raises(ConfigError, match=r"place\.direct_index_level=7 is deeper than the vocabulary"):
        registry.instantiate("place", {**comp.config_node(), "direct_index_level": 7})
    with pytest.raises(ConfigError, match=r"place\.group_min_ratio"):
        DbowPlaceRecognizer(group_min_ratio=2.0)


def test_cli_train_info_convert(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "voc.txt"
    code = main(
        [
            "vocab",
            "train",
            "--synthetic",
            "planar:1000:3",
            "--k",
            "4",
            "--levels",
            "2",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0 and out.read_text().startswith("4 2  0 0\n")
    assert "trained on 3 images / 3000 descriptors" in capsys.readouterr().out
    assert main(["vocab", "convert", str(out), str(tmp_path / "voc.skvoc")]) == 0
    assert load_vocabulary(tmp_path / "voc.skvoc").same_as(load_vocabulary(out))
    assert main(["vocab", "info", str(tmp_path / "voc.skvoc")]) == 0
    assert '"n_nodes"' in capsys.readouterr().out


def test_cli_train_from_image_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    from slamkit.io.synthetic.dataset import SyntheticDataset

    ds = SyntheticDataset(scene="room", seed=5, imu=False, depth=False)
    for i in (0, 100):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), ds[i].image)
    out = tmp_path / "v.skvoc"
    assert (
        main(
            [
                "vocab",
                "train",
                "--images",
                str(tmp_path),
                "--k",
                "3",
                "--levels",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    vocab = load_vocabulary(out)
    assert vocab.metadata["n_images"] == 2 and vocab.metadata["recipe"]["n_image_files"] == 2


def test_cli_bad_input_exit_code(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vocab", "train", "--out", str(tmp_path / "x.skvoc")]) == 2
    assert "give training images" in capsys.readouterr().err
    assert main(["vocab", "train", "--images", str(tmp_path / "none"), "--out", str(tmp_path / "x.skvoc")]) == 2
    assert "training image folder not found" in capsys.readouterr().err
    assert main(["vocab", "info", str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt: vocabulary file not found" in capsys.readouterr().err
    assert main(["vocab", "train", "--synthetic", "room:x", "--out", str(tmp_path / "x.skvoc")]) == 2
    assert "expected SCENE:SEED:N_FRAMES" in capsys.readouterr().err


@pytest.mark.slow
def test_builtin_recipe_reproduces_the_shipped_file(tmp_path: Path) -> None:
    """~30 s: the shipped vocabulary is exactly what its recorded command trains (same library versions)."""
    out = tmp_path / "rebuilt.skvoc"
    assert main(["vocab", "train", "--builtin", "--out", str(out), "--no-progress"]) == 0
    assert out.read_bytes() == shipped_vocabulary_path().read_bytes()
