"""Fuzzed map files (issue 17): a few hundred corrupted files never crash the loader and never load a partial map.

Two kinds: raw damage to the bytes of a saved file (truncations, byte flips, bytes inserted or cut), which the
checksum trailer must catch before anything is parsed; and damage *behind* a valid checksum (a member's values or
length changed, then the file rewritten with a fresh checksum: a buggy or hostile writer), which the manifest and
content checks must catch or, when the change is harmless (a weight, a coordinate), load as a consistent map.
Either way the only exception is MapFileError and the keyframe database gets nothing from a refused file."""

from __future__ import annotations

import functools
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mapfile_atlas import RecordingPlace, build_atlas, build_frames, new_store

from slamkit.errors import MapFileError
from slamkit.map import mapfile
from slamkit.map.mapfile import load_atlas, save_atlas
from slamkit.map.mapfile_contents import check_contents, read_map_contents


@functools.cache
def saved() -> tuple[bytes, dict[str, Any], list[tuple[str, np.ndarray]]]:
    """A saved two-map Atlas with its frames: the file's bytes, its manifest and its members (built once per session)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.slamkit"
        atlas = build_atlas(RecordingPlace())
        save_atlas(atlas, path, frames=build_frames(atlas))  # the sessions' frames are fuzzed too
        with zipfile.ZipFile(path) as zf:
            members = [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]
        return path.read_bytes(), mapfile.read_manifest(path), members


def load_or_refuse(path: Path) -> None:
    """Loads or raises MapFileError; a refused load added nothing to the keyframe database, a load is consistent."""
    place = RecordingPlace()
    try:
        atlas = load_atlas(path, new_store, place)
    except MapFileError as exc:
        assert str(path) in str(exc)
        assert place.added == 0
        return
    for _, store in atlas.items():
        check_contents(read_map_contents(store), atlas.ids)


damage = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0, exclude_max=True), st.just(0)),
    st.tuples(st.just("flip"), st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 255)),
    st.tuples(st.just("insert"), st.floats(0.0, 1.0), st.integers(0, 255)),
    st.tuples(st.just("cut"), st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 64)),
)

FUZZ = settings(
    max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@FUZZ
@given(damages=st.lists(damage, min_size=1, max_size=3))
def test_damaged_bytes_are_refused(tmp_path: Path, damages: list[tuple[str, float, int]]) -> None:
    original = saved()[0]
    data = bytearray(original)
    for kind, where, value in damages:
        at = int(where * len(data))
        if kind == "truncate":
            data = data[:at]
        elif kind == "flip" and data:
            data[min(at, len(data) - 1)] ^= value
        elif kind == "insert":
            data[at:at] = bytes([value])
        elif kind == "cut":
            del data[at : at + value]
    if bytes(data) == original:
        return
    path = tmp_path / "damaged.slamkit"
    path.write_bytes(bytes(data))
    place = RecordingPlace()
    with pytest.raises(MapFileError) as err:
        load_atlas(path, new_store, place)
    assert str(path) in str(err.value) and place.added == 0


@FUZZ
@given(
    member=st.integers(0, 10**6),
    element=st.integers(0, 10**6),
    value=st.one_of(st.integers(-(2**40), 2**40), st.floats(allow_nan=True, allow_infinity=True)),
    shorten=st.booleans(),
)
def test_damage_behind_a_valid_checksum_never_crashes(
    tmp_path: Path, member: int, element: int, value: float, shorten: bool
) -> None:
    _, manifest, members = saved()
    name, array = members[member % len(members)]
    changed = np.array(array)
    if changed.size:
        if shorten and changed.ndim:
            changed = changed[: changed.shape[0] - 1]
        elif changed.dtype.kind in "iu":
            flat = changed.reshape(-1)
            info = np.iinfo(changed.dtype)
            flat[element % flat.size] = max(info.min, min(info.max, int(value))) if np.isfinite(value) else -1
        elif changed.dtype.kind == "f":
            with np.errstate(over="ignore"):
                changed.reshape(-1)[element % changed.size] = value
        elif changed.dtype.kind == "b":
            changed.reshape(-1)[element % changed.size] ^= True
    path = tmp_path / "rewritten.slamkit"
    mapfile._write(path, manifest, [(n, changed if n == name else a) for n, a in members], mapfile.SCHEMA_VERSION)
    load_or_refuse(path)
