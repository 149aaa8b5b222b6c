"""Saved maps: the Atlas in a file that runs no code when it is read (issue 17 item 3).

The format (schema version 1) is an uncompressed zip of ``.npy`` arrays, i.e. a numpy ``.npz`` that ``np.load(path,
allow_pickle=False)`` opens, plus a JSON manifest. Why .npz and not SQLite: the map is a few dozen large columns
(features, descriptors, observations), which numpy writes and reads at disk speed with no per-row cost and no
pickling (object arrays are refused both ways); any numpy user can inspect a file; a zip's comment gives a place for
a checksum over everything before it. SQLite would add per-row inserts (slow for ~10^5 features per 100 keyframes)
and its own journal for the atomicity the os.replace below gives for free.

Members:

- ``manifest.json``: format "slamkit-map", ``schema_version``, ``slamkit_version``, ``created_utc``, the
  vocabulary identity (``PlaceRecognizer.vocabulary_identity()``, e.g. DBoW2's sha256 and word count) the bags of
  words come from, the camera models (``Camera.to_dict()``; keyframes name them by index), the resolved config
  that built the map, the Atlas (active map id, next map id, the IdAllocator's next keyframe and point ids) and,
  per map, its id, sizes, first keyframe and epoch.
- ``m{map_id}/NAME.npy`` per map: keyframes (``kf_*``: ids, frame index, timestamp s, T_c_w (K, 4, 4), camera index,
  the observation record's scalars, feature counts), their features concatenated (``feat_*``: raw and
  pipeline-image pixels, level, angle, response, descriptors, bearing, right coordinate, depth, and the map point
  of each feature), bags of words (``bow_*``: word ids and weights; ``di_*``: direct index nodes and feature
  indices; words and nodes in ascending id, as ``BowDescription`` holds them), map points (``pt_*``: ids, xyz_w,
  normal, depth range, descriptor, reference and first keyframes, visible/found counters; ``obs_*``: observations
  in the store's order), and the graphs (``cov_edges`` (E, 3) with their saved weights, ``tree`` (T, 2)
  child/parent with -1 for a root, ``loop_edges`` (L, 2)). Variable-length parts are concatenated with a count per owner.
- A map of a non-rectified rig (``frontend=stereo_rig``, ORB-SLAM3 sec. I-B; schema version 2, the only difference
  from version 1): per keyframe ``kf_n_left`` (ORB-SLAM3's Nleft, -1 for a one-camera keyframe), ``kf_camera2`` (the
  second camera's index in the manifest's cameras, -1 for none) and ``kf_T_c2_c1`` (K, 4, 4) (the fixed extrinsic,
  ORB-SLAM3 mTrl; identity for none); per feature ``feat_stereo_match`` (the other camera's keypoint of its stereo
  match, -1 for none) and ``feat_xyz_c1`` (F, 3) (the triangulated point in camera 1, NaN elsewhere). A file without
  a two-camera keyframe is written as version 1, as before, and both versions are read.
- ``m{map_id}/fr_*.npy`` per map, optional (files written before them have none, and load with no frames): the
  frames of the sessions that built the map, as ORB-SLAM records a trajectory (System::SaveTrajectoryTUM): ``fr_t_s``
  (N,) timestamps s, ``fr_frame_index`` (N,), ``fr_ref_kf`` (N,) each frame's reference keyframe, a keyframe of the
  map (a culled reference was resolved to a surviving one when the file was written), ``fr_T_c_r`` (N, 4, 4) the
  frame's pose relative to it; the manifest's map entry gives their count (``frames``). A later session's
  trajectory holds them, placed against the keyframes as it leaves them (docs/atlas.md, "Multi-session").

Integrity: the zip comment, the file's last 89 bytes, is ``slamkit-map v0001 sha256=`` and the hex sha256 of every
byte before the 64 hex digits. A reader checks the comment (absent: truncated or not a map file), the schema version
in it, then the checksum, before it parses anything; then the manifest, the vocabulary, and the contents' consistency
(``check_contents``); only then does it build an Atlas. Any failure is a MapFileError naming the file and what is
wrong, and nothing is loaded.

Writing is atomic: the file is written under a temporary name in the same directory, flushed and fsync'ed, then
os.replace'd over the target (and the directory fsync'ed): a crash mid-save leaves the previous file as it was.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import MapFileError
from slamkit.features import Observations
from slamkit.geometry.camera import camera_from_config
from slamkit.interfaces import BowDescription, Camera, DirectIndex, MapStore, PlaceRecognizer, WordWeights
from slamkit.map.atlas import Atlas, StoreFactory
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.mapfile_contents import MapContents
from slamkit.sensors import FrameRecords

#: The layout this code writes for a map without a two-camera keyframe (a change to the members or their meaning
#: bumps it; the optional ``fr_*`` members were added without a bump: files without them load with no frames, and a
#: reader without them ignores them).
SCHEMA_VERSION = 1
#: The layout of a file holding a non-rectified rig's keyframes: version 1 plus the rig members (module docstring), so
#: that a reader that knows version 1 only refuses it rather than losing the second camera.
RIG_SCHEMA_VERSION = 2
_READABLE = (SCHEMA_VERSION, RIG_SCHEMA_VERSION)
FORMAT = "slamkit-map"
#: The suggested file name suffix (and a run directory's map file: ``map.slamkit``).
SUFFIX = ".slamkit"
RUN_DIR_FILE_NAME = "map.slamkit"

_TRAILER_PREFIX = b"slamkit-map v"
_HEX = 64
_TRAILER_LEN = len(_TRAILER_PREFIX) + 4 + len(b" sha256=") + _HEX  # "slamkit-map v0001 sha256=" + hex = 89 bytes
_MANIFEST = "manifest.json"
_SENSORS = ("mono", "stereo", "rgbd")
_CHUNK = 1 << 20


@dataclass(frozen=True)
class MapFileInfo:
    """What ``slamkit map info`` prints: path, size_bytes, schema_version, slamkit_version, created_utc, sha256,
    vocabulary (identity or None), active_map_id, per map (id, keyframes, points), and n_frames: the sessions' frames
    the file keeps (0 for a file written before it kept frames)."""

    path: Path
    size_bytes: int
    schema_version: int
    slamkit_version: str
    created_utc: str
    sha256: str
    vocabulary: dict[str, Any] | None
    active_map_id: int
    maps: tuple[tuple[int, int, int], ...]
    n_frames: int = 0

    @property
    def n_keyframes(self) -> int:
        return sum(k for _, k, _ in self.maps)

    @property
    def n_points(self) -> int:
        return sum(p for _, _, p in self.maps)


# ---- saving ------------------------------------------------------------------------------------------------------


def save_atlas(
    atlas: Atlas,
    path: str | os.PathLike[str],
    config: Mapping[str, Any] | None = None,
    frames: Mapping[int, FrameRecords] | None = None,
) -> MapFileInfo:
    """Write every map of ``atlas`` to ``path`` atomically (see the module docstring); ``config``: the resolved
    config that built the map (JSON-able), kept in the manifest; ``frames``: map id -> the frames of the sessions
    that built it (a runner's ``map_frames()``; None or a map missing: none), each relative to a keyframe of that
    map (a frame whose reference keyframe is not in the map when it is read is left out). Each map is read under its
    read lock. Returns what was written. MapFileError (naming the file) when the path cannot be written or the map
    holds something the format cannot keep (a camera model without ``to_dict``); the previous file at ``path``, if
    any, is untouched."""
    target = Path(path)
    cameras: list[dict[str, Any]] = []
    camera_index: dict[str, int] = {}
    maps_meta: list[dict[str, Any]] = []
    members: list[tuple[str, NDArray[Any]]] = []
    rig_members: list[tuple[str, NDArray[Any]]] = []
    for map_id, store in atlas.items():
        try:
            with store.read():  # the arrays are copies: the map may change again once they are made
                arrays, meta = _map_arrays(store, lambda cam: _camera_id(cam, cameras, camera_index, target))
                rig = _rig_arrays(store, lambda cam: _camera_id(cam, cameras, camera_index, target))
                arrays.update(_frame_arrays((frames or {}).get(map_id), arrays["kf_id"]))
                meta["frames"] = int(arrays["fr_t_s"].shape[0])
        except ValueError as exc:
            raise MapFileError(f"map file {target}: map {map_id} cannot be saved ({exc})") from None
        maps_meta.append({"id": map_id, **meta})
        members += [(f"m{map_id}/{name}.npy", array) for name, array in arrays.items()]
        rig_members += [(f"m{map_id}/{name}.npy", array) for name, array in rig.items()]
    two_cameras = any(bool(np.any(array >= 0)) for name, array in rig_members if name.endswith("/kf_n_left.npy"))
    version = RIG_SCHEMA_VERSION if two_cameras else SCHEMA_VERSION
    if two_cameras:
        members += rig_members
    next_kf, next_pt = atlas.ids.next_ids()
    manifest = {
        "format": FORMAT,
        "schema_version": version,
        "slamkit_version": _slamkit_version(),
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "vocabulary": _vocabulary_identity(atlas.place),
        "cameras": cameras,
        "config": _jsonable(config),
        "atlas": {
            "active_map_id": atlas.active_id,
            "next_map_id": atlas.next_map_id,
            "next_keyframe_id": next_kf,
            "next_point_id": next_pt,
        },
        "maps": maps_meta,
    }
    return _write(target, manifest, members, version)


def _write(
    target: Path, manifest: dict[str, Any], members: Sequence[tuple[str, NDArray[Any]]], schema_version: int
) -> MapFileInfo:
    """The atomic write: temp file in the target's directory, zip members, checksum trailer, fsync, os.replace."""
    directory = target.parent if str(target.parent) else Path(".")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise MapFileError(f"map file {target}: cannot be written ({exc.strerror or exc})") from exc
    tmp = Path(tmp_name)
    try:
        os.fchmod(fd, _file_mode(target))  # mkstemp makes the file 0600; a map file gets the usual mode
        with os.fdopen(fd, "w+b") as f:
            with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                zf.comment = _trailer(schema_version, "0" * _HEX)
                zf.writestr(_MANIFEST, json.dumps(manifest, indent=1, allow_nan=True))
                for name, array in members:
                    with zf.open(name, "w", force_zip64=True) as member:
                        np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
            f.flush()
            size = f.seek(0, io.SEEK_END)
            digest = _sha256_of(f, size - _HEX)
            f.seek(size - _HEX)
            f.write(digest.encode())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise MapFileError(f"map file {target}: cannot be written ({exc.strerror or exc})") from exc
        raise
    _fsync_directory(directory)
    return _info(target, size, digest, manifest)


def _file_mode(target: Path) -> int:
    """The mode of the file being replaced, else 0666 less the umask (what open() would give a new file)."""
    try:
        return target.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def _trailer(schema_version: int, hex_digest: str) -> bytes:
    out = _TRAILER_PREFIX + f"{schema_version:04d} sha256={hex_digest}".encode()
    assert len(out) == _TRAILER_LEN
    return out


def _sha256_of(f: Any, n_bytes: int) -> str:
    """sha256 of the first n_bytes of the open file f, read in chunks (no copy of the file in memory)."""
    h = hashlib.sha256()
    f.seek(0)
    left = n_bytes
    while left > 0:
        chunk = f.read(min(_CHUNK, left))
        if not chunk:
            break
        h.update(chunk)
        left -= len(chunk)
    return h.hexdigest()


def _fsync_directory(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _camera_id(camera: Camera, cameras: list[dict[str, Any]], index: dict[str, int], target: Path) -> int:
    to_dict = getattr(camera, "to_dict", None)
    if not callable(to_dict):
        raise MapFileError(
            f"map file {target}: the camera model {type(camera).__name__} has no to_dict(): it cannot be saved"
        )
    params = to_dict()
    key = json.dumps(params, sort_keys=True)
    if key not in index:
        index[key] = len(cameras)
        cameras.append(params)
    return index[key]


def _vocabulary_identity(place: PlaceRecognizer | None) -> dict[str, Any] | None:
    identity = getattr(place, "vocabulary_identity", None)
    return dict(identity()) if callable(identity) else None


def _slamkit_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("slamkit")
    except PackageNotFoundError:
        return "unknown"


def _jsonable(config: Mapping[str, Any] | None) -> Any:
    if config is None:
        return None
    return json.loads(json.dumps(config, default=str))


def _counts(counts: Iterable[int]) -> NDArray[np.int64]:
    return np.fromiter(counts, np.int64)


def _map_arrays(store: MapStore, camera_id: Callable[[Camera], int]) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """The members of one map and its manifest entry, read through the MapStore protocol (the caller holds the read
    lock) straight into arrays: no copy of the entities, no Python list per element (memory while saving stays
    close to the file's size; benchmarks/map_save_load.py). The same state ``read_map_contents`` describes."""
    kf_ids = store.keyframe_ids()
    kfs = [store.get_keyframe(k) for k in kf_ids]
    feats = [kf.features for kf in kfs]
    K = len(kfs)
    a: dict[str, NDArray[Any]] = {
        "kf_id": np.array(kf_ids, np.int64),
        "kf_frame_index": np.array([kf.frame_index for kf in kfs], np.int64),
        "kf_timestamp_s": np.array([kf.timestamp_s for kf in kfs], np.float64),
        "kf_T_c_w": np.array([kf.T_c_w for kf in kfs], np.float64).reshape(K, 4, 4),
        "kf_camera": np.array([camera_id(kf.camera) for kf in kfs], np.int64),
        "kf_n_features": _counts(len(f) for f in feats),
        "kf_scale_factor": np.array([f.scale_factor for f in feats], np.float64),
        "kf_n_levels": np.array([f.n_levels for f in feats], np.int64),
        "kf_bf": np.array([f.bf for f in feats], np.float64),
        "kf_th_depth_m": np.array([f.th_depth_m for f in feats], np.float64),
        "kf_sensor": np.array([_SENSORS.index(f.sensor) if f.sensor in _SENSORS else -1 for f in feats], np.int64),
    }
    if np.any(a["kf_sensor"] < 0):
        raise ValueError(f"a keyframe's sensor is none of {_SENSORS}")
    width = next((f.descriptors.shape[1] for f in feats if f.descriptors.ndim == 2), 32)
    columns: tuple[tuple[str, type, tuple[int, ...]], ...] = (
        ("uv_px", np.float32, (2,)),
        ("uv_undist_px", np.float32, (2,)),
        ("level", np.int32, ()),
        ("angle_deg", np.float32, ()),
        ("response", np.float32, ()),
        ("descriptors", np.uint8, (width,)),
        ("bearing", np.float64, (3,)),
        ("u_right_px", np.float32, ()),
        ("depth_m", np.float32, ()),
    )
    n_features = int(a["kf_n_features"].sum())
    for name, dtype, tail in columns:
        column: NDArray[Any] = np.empty((n_features, *tail), dtype)
        at = 0
        for f in feats:
            column[at : at + len(f)] = np.asarray(getattr(f, name)).reshape(len(f), *tail)
            at += len(f)
        a[f"feat_{name}"] = column
    a["feat_point_id"] = np.concatenate([kf.point_ids for kf in kfs]) if kfs else np.zeros(0, np.int64)
    # bags of words: each one's arrays (words by ascending id, the order a score sums them in; direct-index nodes by
    # ascending id), written as int64 / float64 columns as they always were
    bows = [kf.bow for kf in kfs]
    a["kf_has_bow"] = np.array([b is not None for b in bows], np.bool_)
    words = [b.word_weights for b in bows if b is not None]
    direct = [b.direct for b in bows if b is not None]
    a["bow_n_words"] = _counts(len(b.words) if b is not None else 0 for b in bows)
    a["bow_word"] = _joined([w.ids for w in words], np.int64)
    a["bow_weight"] = _joined([w.weights for w in words], np.float64)
    a["di_n_nodes"] = _counts(len(b.direct_index) if b is not None else 0 for b in bows)
    a["di_node"] = _joined([d.nodes for d in direct], np.int64)
    a["di_n_features"] = _joined([np.diff(d.offsets) for d in direct], np.int64)
    a["di_feature"] = _joined([d.features for d in direct], np.int64)
    pids = np.array(store.point_ids(), np.int64)
    pts = store.get_points(pids.tolist())
    P = len(pts)

    def rows(attribute: str, dtype: type, tail: tuple[int, ...]) -> NDArray[Any]:
        if not P:
            return np.zeros((0, *tail), dtype)
        return np.asarray(store.point_rows(pids, attribute), dtype).reshape(P, *tail)

    a["pt_id"] = pids
    a["pt_xyz_w"] = rows("xyz_w", np.float64, (3,))
    a["pt_normal_w"] = rows("normal_w", np.float64, (3,))
    a["pt_d_min_m"] = rows("d_min_m", np.float64, ())
    a["pt_d_max_m"] = rows("d_max_m", np.float64, ())
    a["pt_descriptor"] = rows("descriptor", np.uint8, (pts[0].descriptor.shape[0] if P else width,))
    a["pt_ref_kf"] = np.fromiter((p.ref_kf_id for p in pts), np.int64, P)
    a["pt_first_kf"] = np.fromiter((p.first_kf_id for p in pts), np.int64, P)
    a["pt_n_visible"] = rows("n_visible", np.int64, ())
    a["pt_n_found"] = rows("n_found", np.int64, ())
    a["pt_n_obs"] = _counts(len(p.observations) for p in pts)
    n_obs = int(a["pt_n_obs"].sum())
    a["obs_kf"] = np.fromiter((k for p in pts for k in p.observations), np.int64, n_obs)
    a["obs_feature"] = np.fromiter((i for p in pts for i in p.observations.values()), np.int64, n_obs)
    edges = store.covisibility.edges()
    a["cov_edges"] = np.array(edges, np.int64).reshape(len(edges), 3)
    tree = store.spanning_tree
    a["tree"] = np.array([(k, _parent_or_root(tree.parent(k))) for k in kf_ids if k in tree], np.int64).reshape(-1, 2)
    a["loop_edges"] = np.array(store.loop_edges(), np.int64).reshape(-1, 2)
    meta = {
        "keyframes": K,
        "points": P,
        "features": n_features,
        "descriptor_bytes": int(a["pt_descriptor"].shape[1]) if P else int(width),
        "first_keyframe_id": kf_ids[0] if kf_ids else None,
        "epoch": int(store.epoch),
    }
    if P and K and a["pt_descriptor"].shape[1] != a["feat_descriptors"].shape[1]:
        raise ValueError("the map points' descriptors and the keyframes' differ in width")
    return a, meta


def _rig_arrays(store: MapStore, camera_id: Callable[[Camera], int]) -> dict[str, NDArray[Any]]:
    """The rig members of one map (module docstring), in the keyframe and feature order of ``_map_arrays``: for a
    one-camera keyframe n_left -1, no second camera, the identity extrinsic, no stereo matches, NaN points."""
    kfs = [store.get_keyframe(k) for k in store.keyframe_ids()]
    K = len(kfs)
    n_left = np.full(K, -1, np.int64)
    camera2 = np.full(K, -1, np.int64)
    T_c2_c1 = np.tile(np.eye(4), (K, 1, 1))
    matches: list[NDArray[np.int64]] = []
    xyz: list[NDArray[np.float64]] = []
    for i, kf in enumerate(kfs):
        f = kf.features
        n = len(f)
        if f.two_cameras:
            if f.camera_2 is None or f.T_c2_c1 is None or f.stereo_match is None or f.xyz_c1 is None:
                raise ValueError(f"keyframe {kf.id}: a two-camera record without its second camera's fields")
            n_left[i], camera2[i] = f.n_left, camera_id(f.camera_2)
            T_c2_c1[i] = np.asarray(f.T_c2_c1, np.float64)
            matches.append(np.asarray(f.stereo_match, np.int64).reshape(n))
            xyz.append(np.asarray(f.xyz_c1, np.float64).reshape(n, 3))
        else:
            matches.append(np.full(n, -1, np.int64))
            xyz.append(np.full((n, 3), np.nan))
    return {
        "kf_n_left": n_left,
        "kf_camera2": camera2,
        "kf_T_c2_c1": T_c2_c1.reshape(K, 4, 4),
        "feat_stereo_match": np.concatenate(matches) if matches else np.zeros(0, np.int64),
        "feat_xyz_c1": np.concatenate(xyz) if xyz else np.zeros((0, 3)),
    }


def _frame_arrays(records: FrameRecords | None, kf_ids: NDArray[np.int64]) -> dict[str, NDArray[Any]]:
    """The ``fr_*`` members of one map: ``records`` without the frames whose reference keyframe is not one of the
    map's ``kf_ids`` (None: no frame)."""
    if records is None:
        records = FrameRecords.empty()
    keep = np.isin(records.ref_kf_id, kf_ids)
    return {
        "fr_t_s": np.asarray(records.t_s, np.float64)[keep],
        "fr_frame_index": np.asarray(records.frame_index, np.int64)[keep],
        "fr_ref_kf": np.asarray(records.ref_kf_id, np.int64)[keep],
        "fr_T_c_r": np.asarray(records.T_c_r, np.float64)[keep].reshape(-1, 4, 4),
    }


def _parent_or_root(parent: int | None) -> int:
    return -1 if parent is None else int(parent)


# ---- reading ------------------------------------------------------------------------------------------------------


def _open_verified(path: Path) -> tuple[BinaryIO, int, str]:
    """The open file after the trailer, schema version and checksum checks (read in chunks: the file is never held
    in memory whole): (file, size in bytes, sha256). The caller reads the zip from this same open file, so what
    was checked is what is parsed (a writer replaces the file by os.replace: a new file, not this one)."""
    try:
        f = path.open("rb")
    except FileNotFoundError:
        raise MapFileError(f"map file {path}: no such file") from None
    except OSError as exc:
        raise MapFileError(f"map file {path}: cannot be read ({exc.strerror or exc})") from exc
    try:
        size = f.seek(0, io.SEEK_END)
        f.seek(max(size - _TRAILER_LEN, 0))
        trailer = f.read(_TRAILER_LEN)
        if size < _TRAILER_LEN or not trailer.startswith(_TRAILER_PREFIX):
            raise MapFileError(
                f"map file {path}: truncated or not a slamkit map file (no '{_TRAILER_PREFIX.decode()}' trailer at "
                "its end)"
            )
        try:
            version = int(trailer[len(_TRAILER_PREFIX) : len(_TRAILER_PREFIX) + 4].decode("ascii"))
            expected = trailer[-_HEX:].decode("ascii")
        except (ValueError, UnicodeDecodeError):
            raise MapFileError(f"map file {path}: corrupted (unreadable trailer)") from None
        if trailer[len(_TRAILER_PREFIX) + 4 : -_HEX] != b" sha256=":
            raise MapFileError(f"map file {path}: corrupted (unreadable trailer)")
        if version not in _READABLE:
            raise MapFileError(
                f"map file {path}: schema version {version}, this slamkit ({_slamkit_version()}) reads schema "
                f"versions {', '.join(map(str, _READABLE))} only"
            )
        actual = _sha256_of(f, size - _HEX)
        if actual != expected:
            raise MapFileError(
                f"map file {path}: checksum mismatch (sha256 {actual[:12]}..., the file says {expected[:12]}...): the "
                "file is corrupted or incomplete"
            )
    except BaseException:
        f.close()
        raise
    return f, size, actual


def _trailer_version(f: BinaryIO, size: int) -> int:
    """The schema version in the (already verified) trailer of the open file of ``size`` bytes."""
    f.seek(size - _TRAILER_LEN + len(_TRAILER_PREFIX))
    return int(f.read(4).decode("ascii"))


class _Reader:
    """The verified zip: the manifest and the arrays of each map, checked for dtype and shape as they are read.
    A context manager (closes the file)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.file, self.size, self.sha256 = _open_verified(path)
        try:
            self.zip = zipfile.ZipFile(self.file)
            manifest = json.loads(self.zip.read(_MANIFEST))
        except (zipfile.BadZipFile, KeyError, ValueError, OSError) as exc:
            self.file.close()
            raise self.error(f"unreadable container or manifest ({exc})") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            self.file.close()
            raise self.error(f"not a {FORMAT} manifest")
        trailer_version = int(_trailer_version(self.file, self.size))
        if manifest.get("schema_version") != trailer_version:
            self.file.close()
            raise self.error(
                f"manifest schema version {manifest.get('schema_version')!r}, the trailer says {trailer_version}"
            )
        self.manifest: dict[str, Any] = manifest
        #: the file holds the rig members (schema version 2)
        self.rig = trailer_version == RIG_SCHEMA_VERSION

    def __enter__(self) -> _Reader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.zip.close()
        self.file.close()

    def error(self, what: str) -> MapFileError:
        return MapFileError(f"map file {self.path}: {what}")

    def array(
        self, map_id: int, name: str, dtype: type, tail: tuple[int, ...], rows: int | None = None
    ) -> NDArray[Any]:
        member = f"m{map_id}/{name}.npy"
        try:
            with self.zip.open(member) as f:
                out = np.lib.format.read_array(f, allow_pickle=False)
        except KeyError:
            raise self.error(f"map {map_id}: member {member} is missing") from None
        except (ValueError, OSError, zipfile.BadZipFile) as exc:
            raise self.error(f"map {map_id}: member {member} unreadable ({exc})") from None
        if out.dtype != np.dtype(dtype) or out.shape[1:] != tail or (rows is not None and out.shape[0] != rows):
            want = f"({'rows' if rows is None else rows}, {', '.join(map(str, tail))}) {np.dtype(dtype)}"
            raise self.error(f"map {map_id}: {name} is {out.shape} {out.dtype}, expected {want}")
        out.setflags(write=False)
        return out


def _joined(parts: Sequence[NDArray[Any]], dtype: type) -> NDArray[Any]:
    """The 1-D arrays ``parts`` end to end as ``dtype`` (an empty array of it when there are none)."""
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)


def _read_bow(
    word: NDArray[np.int64], weight: NDArray[np.float64], nodes: NDArray[np.int64], groups: Sequence[NDArray[np.int64]]
) -> BowDescription:
    """A keyframe's bag of words from its rows of the file: words (K,) and their weights (K,), direct-index nodes (G,)
    and each node's feature indices. Rows come in ascending id from slamkit's writer; any other order is sorted."""
    if word.size > 1 and not bool(np.all(word[1:] > word[:-1])):
        return BowDescription(
            dict(zip(word.tolist(), weight.tolist(), strict=True)),
            {n: g for n, g in zip(nodes.tolist(), groups, strict=True)},
        )
    direct: Mapping[int, NDArray[np.integer]]
    if nodes.size > 1 and not bool(np.all(nodes[1:] > nodes[:-1])):
        direct = {n: g for n, g in zip(nodes.tolist(), groups, strict=True)}
    else:
        offsets = np.zeros(nodes.shape[0] + 1, np.int64)
        np.cumsum([g.shape[0] for g in groups], out=offsets[1:])
        direct = DirectIndex(nodes, offsets, _joined(list(groups), np.int32))
    return BowDescription(WordWeights(word, weight), direct)


def _split(array: NDArray[Any], counts: NDArray[np.int64], what: str, reader: _Reader) -> list[NDArray[Any]]:
    if np.any(counts < 0) or int(counts.sum()) != array.shape[0]:
        raise reader.error(f"{what}: counts add up to {int(counts.sum())}, the array has {array.shape[0]} rows")
    return np.split(array, np.cumsum(counts)[:-1]) if counts.size else []


def _read_map(reader: _Reader, meta: Mapping[str, Any], cameras: Sequence[Camera]) -> MapContents:
    m = int(meta["id"])
    K, P = int(meta["keyframes"]), int(meta["points"])
    F, D = int(meta["features"]), int(meta["descriptor_bytes"])

    def arr(name: str, dtype: type, tail: tuple[int, ...] = (), rows: int | None = None) -> NDArray[Any]:
        return reader.array(m, name, dtype, tail, rows)

    kf_id = arr("kf_id", np.int64, rows=K)
    frame_index = arr("kf_frame_index", np.int64, rows=K)
    timestamp = arr("kf_timestamp_s", np.float64, rows=K)
    T_c_w = arr("kf_T_c_w", np.float64, (4, 4), K)
    camera = arr("kf_camera", np.int64, rows=K)
    if K and (camera.min() < 0 or camera.max() >= len(cameras)):
        raise reader.error(f"map {m}: a keyframe names a camera the manifest does not list")
    scale_factor = arr("kf_scale_factor", np.float64, rows=K)
    n_levels = arr("kf_n_levels", np.int64, rows=K)
    bf = arr("kf_bf", np.float64, rows=K)
    th_depth = arr("kf_th_depth_m", np.float64, rows=K)
    sensor = arr("kf_sensor", np.int64, rows=K)
    if K and (sensor.min() < 0 or sensor.max() >= len(_SENSORS)):
        raise reader.error(f"map {m}: a keyframe's sensor code is out of range")
    n_feat = arr("kf_n_features", np.int64, rows=K)
    cols = {
        "uv_px": (np.float32, (2,)),
        "uv_undist_px": (np.float32, (2,)),
        "level": (np.int32, ()),
        "angle_deg": (np.float32, ()),
        "response": (np.float32, ()),
        "descriptors": (np.uint8, (D,)),
        "bearing": (np.float64, (3,)),
        "u_right_px": (np.float32, ()),
        "depth_m": (np.float32, ()),
        "point_id": (np.int64, ()),
    }
    per_kf = {name: _split(arr(f"feat_{name}", dt, tail, F), n_feat, f"map {m} features", reader)
              for name, (dt, tail) in cols.items()}  # fmt: skip
    has_bow = arr("kf_has_bow", np.bool_, rows=K)
    n_words = arr("bow_n_words", np.int64, rows=K)
    words = _split(arr("bow_word", np.int64), n_words, f"map {m} bow words", reader)
    weights = _split(arr("bow_weight", np.float64, rows=int(n_words.sum())), n_words, f"map {m} bow", reader)
    n_nodes = arr("di_n_nodes", np.int64, rows=K)
    nodes = arr("di_node", np.int64)
    node_groups = _split(nodes, n_nodes, f"map {m} direct index", reader)
    n_di = arr("di_n_features", np.int64, rows=nodes.shape[0])
    groups = _split(arr("di_feature", np.int64), n_di, f"map {m} direct index features", reader)
    rig = _read_rig(reader, m, K, F, n_feat, cameras)
    keyframes: list[KeyFrame] = []
    g = 0
    for i in range(K):
        obs = Observations(
            uv_px=per_kf["uv_px"][i],
            uv_undist_px=per_kf["uv_undist_px"][i],
            level=per_kf["level"][i],
            angle_deg=per_kf["angle_deg"][i],
            response=per_kf["response"][i],
            descriptors=per_kf["descriptors"][i],
            scale_factor=float(scale_factor[i]),
            n_levels=int(n_levels[i]),
            bearing=per_kf["bearing"][i],
            u_right_px=per_kf["u_right_px"][i],
            depth_m=per_kf["depth_m"][i],
            bf=float(bf[i]),
            th_depth_m=float(th_depth[i]),
            sensor=_SENSORS[int(sensor[i])],
            **rig[i],
        )
        bow: BowDescription | None = None
        k_nodes = node_groups[i]
        if has_bow[i]:
            bow = _read_bow(words[i], weights[i], k_nodes, groups[g : g + k_nodes.shape[0]])
        g += k_nodes.shape[0]
        keyframes.append(
            KeyFrame(
                int(kf_id[i]),
                int(frame_index[i]),
                float(timestamp[i]),
                T_c_w[i],
                cameras[int(camera[i])],
                obs,
                per_kf["point_id"][i],
                bow,
            )
        )
    n_obs = arr("pt_n_obs", np.int64, rows=P)
    obs_kf = _split(arr("obs_kf", np.int64), n_obs, f"map {m} observations", reader)
    obs_feat = _split(arr("obs_feature", np.int64, rows=int(n_obs.sum())), n_obs, f"map {m} observations", reader)
    pt_id = arr("pt_id", np.int64, rows=P)
    xyz = arr("pt_xyz_w", np.float64, (3,), P)
    normal = arr("pt_normal_w", np.float64, (3,), P)
    d_min = arr("pt_d_min_m", np.float64, rows=P)
    d_max = arr("pt_d_max_m", np.float64, rows=P)
    descriptor = arr("pt_descriptor", np.uint8, (D,), P)
    ref_kf = arr("pt_ref_kf", np.int64, rows=P)
    first_kf = arr("pt_first_kf", np.int64, rows=P)
    points = [
        MapPoint(
            int(pt_id[i]),
            xyz[i],
            descriptor[i],
            int(ref_kf[i]),
            int(first_kf[i]),
            normal[i],
            float(d_min[i]),
            float(d_max[i]),
            dict(zip(obs_kf[i].tolist(), obs_feat[i].tolist(), strict=True)),
        )
        for i in range(P)
    ]
    tree = arr("tree", np.int64, (2,))
    first = meta.get("first_keyframe_id")
    return MapContents(
        keyframes=tuple(keyframes),
        points=tuple(points),
        n_visible=np.array(arr("pt_n_visible", np.int64, rows=P)),
        n_found=np.array(arr("pt_n_found", np.int64, rows=P)),
        covisibility=np.array(arr("cov_edges", np.int64, (3,))),
        tree={int(k): (None if p < 0 else int(p)) for k, p in tree.tolist()},
        loop_edges=tuple((int(a), int(b)) for a, b in arr("loop_edges", np.int64, (2,)).tolist()),
        first_keyframe_id=None if first is None else int(first),
        epoch=int(meta.get("epoch", 0)),
    )


def _read_rig(
    reader: _Reader, m: int, K: int, F: int, n_feat: NDArray[np.int64], cameras: Sequence[Camera]
) -> list[dict[str, Any]]:
    """Per keyframe of map ``m``, the two-camera fields of its Observations (empty for a one-camera keyframe, and for
    every keyframe of a version-1 file), with their consistency checked: n_left within the features, a listed
    second camera, a rigid extrinsic, stereo matches linking a camera-1 and a camera-2 keypoint both ways."""
    if not reader.rig:
        return [{} for _ in range(K)]
    n_left = reader.array(m, "kf_n_left", np.int64, (), K)
    camera2 = reader.array(m, "kf_camera2", np.int64, (), K)
    T_c2_c1 = reader.array(m, "kf_T_c2_c1", np.float64, (4, 4), K)
    matches = _split(reader.array(m, "feat_stereo_match", np.int64, (), F), n_feat, f"map {m} stereo matches", reader)
    xyz = _split(reader.array(m, "feat_xyz_c1", np.float64, (3,), F), n_feat, f"map {m} stereo points", reader)
    out: list[dict[str, Any]] = []
    for i in range(K):
        if n_left[i] < 0:
            out.append({})
            continue
        n = int(n_feat[i])
        if n_left[i] > n or not 0 <= camera2[i] < len(cameras):
            raise reader.error(f"map {m}: keyframe {i}'s n_left or second camera is out of range")
        T = T_c2_c1[i]
        if not (np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) and np.allclose(T[3], [0, 0, 0, 1])):
            raise reader.error(f"map {m}: keyframe {i}'s T_c2_c1 is not a rigid transform")
        sm = matches[i]
        linked = np.flatnonzero(sm >= 0)
        left = linked < n_left[i]
        if np.any(sm >= n) or np.any((sm[linked] < n_left[i]) == left) or np.any(sm[sm[linked]] != linked):
            raise reader.error(f"map {m}: keyframe {i}'s stereo matches do not link camera 1 and 2 both ways")
        out.append(
            {
                "n_left": int(n_left[i]),
                "stereo_match": sm,
                "xyz_c1": xyz[i],
                "camera_2": cameras[int(camera2[i])],
                "T_c2_c1": T,
            }
        )
    return out


def _read_frames(reader: _Reader, meta: Mapping[str, Any], contents: MapContents) -> FrameRecords | None:
    """A map's ``fr_*`` members (None when the manifest lists no frames for it: a file written before they were
    kept), checked: finite timestamps and rigid-looking relative poses, every reference a keyframe of the map."""
    if "frames" not in meta:
        return None
    m, n = int(meta["id"]), int(meta["frames"])
    if n < 0:
        raise reader.error(f"map {m}: {n} frames")
    t_s = reader.array(m, "fr_t_s", np.float64, (), n)
    index = reader.array(m, "fr_frame_index", np.int64, (), n)
    ref = reader.array(m, "fr_ref_kf", np.int64, (), n)
    T_c_r = reader.array(m, "fr_T_c_r", np.float64, (4, 4), n)
    if not (np.all(np.isfinite(t_s)) and np.all(np.isfinite(T_c_r))):
        raise reader.error(f"map {m}: a frame's timestamp or pose is not finite")
    if n and not np.array_equal(T_c_r[:, 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (n, 4))):
        raise reader.error(f"map {m}: a frame's relative pose is not a 4x4 rigid transform (last row)")
    kf_ids = np.array([kf.id for kf in contents.keyframes], np.int64)
    if not np.all(np.isin(ref, kf_ids)):
        bad = int(ref[~np.isin(ref, kf_ids)][0])
        raise reader.error(f"map {m}: a frame's reference keyframe {bad} is not a keyframe of the map")
    return FrameRecords(np.array(t_s), np.array(index), np.array(ref), np.array(T_c_r))


def _cameras(reader: _Reader, reuse: Sequence[Camera]) -> list[Camera]:
    """The manifest's cameras; one whose parameters equal a camera of ``reuse`` (the run's) is that object."""
    known = {}
    for cam in reuse:
        to_dict = getattr(cam, "to_dict", None)
        if callable(to_dict):
            known[json.dumps(to_dict(), sort_keys=True)] = cam
    out: list[Camera] = []
    for i, params in enumerate(reader.manifest.get("cameras", [])):
        key = json.dumps(params, sort_keys=True)
        if key in known:
            out.append(known[key])
            continue
        try:
            out.append(camera_from_config(params, key=f"cameras[{i}]"))
        except Exception as exc:
            raise reader.error(f"camera {i}: {exc}") from None
    return out


def _check_vocabulary(reader: _Reader, place: PlaceRecognizer | None) -> None:
    saved: dict[str, Any] | None = reader.manifest.get("vocabulary")
    if place is None:
        return  # no keyframe database to fill: the bags of words stay on the keyframes, unused
    run = _vocabulary_identity(place)
    if saved is None and run is None:
        return
    if saved is None:
        raise reader.error("it records no vocabulary; the run's place recognizer needs one it can check")
    if run is None:
        raise reader.error(
            f"its bags of words come from vocabulary {saved.get('sha256', '?')[:12]}..., and the run's place "
            f"recognizer ({type(place).__name__}) cannot tell its vocabulary (no vocabulary_identity())"
        )
    if saved.get("sha256") != run.get("sha256"):
        raise reader.error(
            f"written with another vocabulary ({saved.get('name', '?')}: {saved.get('words', '?')} words, sha256 "
            f"{str(saved.get('sha256'))[:12]}...) than the run's ({run.get('name', '?')}: {run.get('words', '?')} "
            f"words, sha256 {str(run.get('sha256'))[:12]}...)"
        )


def load_atlas(
    path: str | os.PathLike[str],
    new_store: StoreFactory,
    place: PlaceRecognizer | None,
    cameras: Sequence[Camera] = (),
) -> Atlas:
    """The Atlas saved in ``path``: every map restored into a store built by ``new_store`` (the run's ``map=``
    component), its keyframes added to the keyframe database ``place`` (which must use the vocabulary the file was
    written with). ``cameras``: the run's cameras; a saved camera with the same parameters is that object.
    MapFileError naming the file and the fault; nothing is added to ``place`` then."""
    with _Reader(Path(path)) as reader:
        return _load(reader, new_store, place, cameras)


def _load(reader: _Reader, new_store: StoreFactory, place: PlaceRecognizer | None, cameras: Sequence[Camera]) -> Atlas:
    _check_vocabulary(reader, place)
    manifest = reader.manifest
    try:
        atlas_meta = manifest["atlas"]
        cams = _cameras(reader, cameras)
        maps = [(int(meta["id"]), _read_map(reader, meta, cams)) for meta in manifest["maps"]]
        frames = {
            map_id: records
            for meta, (map_id, contents) in zip(manifest["maps"], maps, strict=True)
            if (records := _read_frames(reader, meta, contents)) is not None
        }
        ids = IdAllocator(int(atlas_meta["next_keyframe_id"]), int(atlas_meta["next_point_id"]))
        atlas = Atlas.restore(
            new_store, place, ids, maps, int(atlas_meta["active_map_id"]), int(atlas_meta["next_map_id"])
        )
        atlas.loaded_frames = frames
        return atlas
    except MapFileError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise reader.error(f"inconsistent contents ({type(exc).__name__}: {exc})") from None


def resolve_map_path(path: str | os.PathLike[str]) -> Path:
    """A map file given as itself or as the run directory holding it (``map.save=true`` writes ``map.slamkit`` there)."""
    p = Path(path).expanduser()
    return p / RUN_DIR_FILE_NAME if p.is_dir() else p


def read_atlas(path: str | os.PathLike[str], place: PlaceRecognizer | None = None) -> Atlas:
    """The Atlas saved in ``path`` in in-memory stores (``map=memory``, with the saved config's
    ``map.covisibility_min_shared``), for tools that read a map outside a run (exporters, notebooks): no keyframe
    database unless ``place`` is given. The same checks and MapFileError as ``load_atlas``."""
    from slamkit.map.store import InMemoryMapStore

    with _Reader(Path(path)) as reader:
        config = reader.manifest.get("config") or {}
        node = config.get("map") if isinstance(config, dict) else None
        min_shared = node.get("covisibility_min_shared", 15) if isinstance(node, dict) else 15
        try:
            min_shared = int(min_shared)
        except (TypeError, ValueError):
            min_shared = 15
        return _load(reader, lambda ids: InMemoryMapStore(max(min_shared, 1), ids=ids), place, ())


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of a verified map file (trailer, schema version, checksum checked)."""
    with _Reader(Path(path)) as reader:
        return dict(reader.manifest)


def map_file_info(path: str | os.PathLike[str]) -> MapFileInfo:
    """What the file holds (after the same checks a load makes of the container: trailer, schema, checksum)."""
    with _Reader(Path(path)) as reader:
        return _info(reader.path, reader.size, reader.sha256, reader.manifest)


def _info(path: Path, size: int, sha256: str, manifest: Mapping[str, Any]) -> MapFileInfo:
    try:
        return MapFileInfo(
            path=path,
            size_bytes=int(size),
            schema_version=int(manifest["schema_version"]),
            slamkit_version=str(manifest.get("slamkit_version", "?")),
            created_utc=str(manifest.get("created_utc", "?")),
            sha256=sha256,
            vocabulary=manifest.get("vocabulary"),
            active_map_id=int(manifest["atlas"]["active_map_id"]),
            maps=tuple((int(m["id"]), int(m["keyframes"]), int(m["points"])) for m in manifest["maps"]),
            n_frames=sum(int(m.get("frames", 0)) for m in manifest["maps"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFileError(f"map file {path}: malformed manifest ({type(exc).__name__}: {exc})") from None


__all__ = [
    "RIG_SCHEMA_VERSION",
    "RUN_DIR_FILE_NAME",
    "SCHEMA_VERSION",
    "SUFFIX",
    "MapFileInfo",
    "load_atlas",
    "map_file_info",
    "read_atlas",
    "read_manifest",
    "resolve_map_path",
    "save_atlas",
]
