"""Map export (issue 18.3) on hand-made maps with exact geometry: the PLY read back with plyfile, the COLMAP model
with pycolmap (its cameras project the points where slamkit's cameras do, in COLMAP's pixel convention), the TUM
file with slamkit's reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from export_maps import DISTORTED, DISTORTED_K3, FISHEYE, PINHOLE, StripeImages, build_map

from slamkit.errors import ExportError
from slamkit.export import export_map
from slamkit.export.colours import NO_COLOUR_RGB
from slamkit.interfaces import Camera
from slamkit.io.trajectory_io import read_trajectory
from slamkit.map.atlas import Atlas
from slamkit.map.store import InMemoryMapStore

plyfile = pytest.importorskip("plyfile", reason="plyfile (dev extra) reads the PLY back")
pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (dev extra) reads the COLMAP model back")


@pytest.fixture
def store() -> InMemoryMapStore:
    s = InMemoryMapStore()
    build_map(PINHOLE, s)
    return s


def test_ply_has_every_point_with_its_position_colour_and_map(tmp_path: Path, store: InMemoryMapStore) -> None:
    images = StripeImages(640, 480)
    export_map(store, "ply", tmp_path / "map.ply", colours=images)
    data = plyfile.PlyData.read(str(tmp_path / "map.ply"))
    assert data.elements[0].name == "vertex" and not data.text and data.byte_order == "<"
    v = data["vertex"]
    assert len(v) == store.n_points()
    ids = np.array(store.point_ids())
    assert np.array_equal(np.asarray(v["point_id"]), ids)
    xyz = np.column_stack([v["x"], v["y"], v["z"]])
    assert np.array_equal(xyz, store.point_rows(ids, "xyz_w"))  # float64, bit for bit
    assert set(np.asarray(v["map_id"]).tolist()) == {0}
    # colour: the mean over the observations of the image at the nearest pixel
    for row, pid in enumerate(ids.tolist()):
        point = store.get_point(pid)
        samples = []
        for kf_id, feat in point.observations.items():
            kf = store.get_keyframe(kf_id)
            u, v_ = np.rint(kf.features.uv_px[feat]).astype(int)
            samples.append(images.rgb(kf.frame_index)[v_, u])
        expected = np.rint(np.mean(samples, axis=0))
        assert [v["red"][row], v["green"][row], v["blue"][row]] == expected.tolist()


def test_ply_without_images_is_grey_and_tells_maps_apart(tmp_path: Path) -> None:
    first = InMemoryMapStore()
    build_map(PINHOLE, first, n_points=20)
    atlas = Atlas(lambda ids: InMemoryMapStore(ids=ids), first=first)
    atlas.create_map()
    build_map(PINHOLE, atlas.active, n_points=35, seed=1, frame0=100)
    export_map(atlas, "ply", tmp_path / "atlas.ply")
    v = plyfile.PlyData.read(str(tmp_path / "atlas.ply"))["vertex"]
    assert len(v) == 55
    assert np.bincount(np.asarray(v["map_id"])).tolist() == [20, 35]
    assert {(r, g, b) for r, g, b in zip(v["red"], v["green"], v["blue"], strict=True)} == {NO_COLOUR_RGB}


@pytest.mark.parametrize(
    ("camera", "model"),
    [(PINHOLE, "PINHOLE"), (DISTORTED, "OPENCV"), (DISTORTED_K3, "FULL_OPENCV"), (FISHEYE, "OPENCV_FISHEYE")],
)
def test_colmap_model_loads_with_the_keyframe_poses_and_projects_as_slamkit(
    tmp_path: Path, camera: Camera, model: str
) -> None:
    store = InMemoryMapStore()
    build_map(camera, store)
    export_map(store, "colmap", tmp_path / "model", colours=StripeImages(camera.width, camera.height))
    rec = pycolmap.Reconstruction(str(tmp_path / "model"))
    assert len(rec.cameras) == 1 and rec.cameras[1].model_name == model
    assert sorted(rec.images) == store.keyframe_ids()
    assert sorted(rec.points3D) == store.point_ids()
    for kf_id, image in rec.images.items():
        kf = store.get_keyframe(kf_id)
        assert image.name == f"frame_{kf.frame_index:06d}.png"
        np.testing.assert_allclose(image.projection_center(), kf.center_w, rtol=0, atol=1e-12)
        np.testing.assert_allclose(image.cam_from_world().matrix(), kf.T_c_w[:3, :4], rtol=0, atol=1e-12)
        assert image.num_points2D() == kf.features.uv_px.shape[0]
        observed = {i: p.point3D_id for i, p in enumerate(image.points2D) if p.has_point3D()}
        assert observed == {f: pid for f, pid in enumerate(kf.point_ids.tolist()) if pid >= 0}
    cam = rec.cameras[1]
    for pid, point in rec.points3D.items():
        assert np.array_equal(point.xyz, store.get_point(pid).xyz_w)
        track = sorted((e.image_id, e.point2D_idx) for e in point.track.elements)
        assert track == sorted(store.get_point(pid).observations.items())
        assert 0 <= point.error < 1e-3  # features are the exact projections (float32 pixels)
        for kf_id, feat in track:
            # COLMAP's camera projects the point at slamkit's feature pixel + 0.5 (its pixel-centre convention)
            image = rec.images[kf_id]
            xyz_c = image.cam_from_world() * point.xyz
            uv_colmap = cam.img_from_cam(xyz_c.reshape(1, 3)).reshape(2)
            uv_slamkit = store.get_keyframe(kf_id).features.uv_px[feat].astype(np.float64)
            np.testing.assert_allclose(uv_colmap, uv_slamkit + 0.5, rtol=0, atol=2e-3)


def test_colmap_writes_the_keyframe_images_and_one_model_per_map(tmp_path: Path) -> None:
    first = InMemoryMapStore()
    build_map(PINHOLE, first, n_points=20)
    atlas = Atlas(lambda ids: InMemoryMapStore(ids=ids), first=first)
    atlas.create_map()
    build_map(PINHOLE, atlas.active, n_points=35, seed=1, frame0=100)
    images = StripeImages(640, 480)
    result = export_map(atlas, "colmap", tmp_path / "sparse", colours=images, maps="all", images_dir=tmp_path / "img")
    assert result.paths == [tmp_path / "sparse" / "0", tmp_path / "sparse" / "1"]
    assert [len(pycolmap.Reconstruction(str(p)).points3D) for p in result.paths] == [20, 35]
    assert result.images_written == 6
    import cv2

    bgr = cv2.imread(str(tmp_path / "img" / "frame_000103.png"), cv2.IMREAD_COLOR)
    assert np.array_equal(bgr[:, :, ::-1], images.rgb(103))
    # default: the main map (most keyframes; ties: lowest id), as keyframes.tum
    main = export_map(atlas, "colmap", tmp_path / "main")
    assert main.maps == [(0, 3, 20)]


def test_tum_is_the_keyframe_trajectory(tmp_path: Path, store: InMemoryMapStore) -> None:
    export_map(store, "tum", tmp_path / "kf.tum")
    traj = read_trajectory(tmp_path / "kf.tum", "tum")
    kfs = [store.get_keyframe(k) for k in store.keyframe_ids()]
    assert traj.t_s.tolist() == [kf.timestamp_s for kf in kfs]
    np.testing.assert_allclose(traj.T_w_c, np.stack([kf.T_w_c for kf in kfs]), rtol=0, atol=1e-12)


def test_clear_errors(tmp_path: Path, store: InMemoryMapStore) -> None:
    with pytest.raises(ExportError, match="format 'obj'"):
        export_map(store, "obj", tmp_path / "x")
    with pytest.raises(ExportError, match="map 7 is not in the Atlas"):
        export_map(store, "ply", tmp_path / "x.ply", maps=7)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ExportError, match=str(blocker / "x.ply")):
        export_map(store, "ply", blocker / "x.ply")
    with pytest.raises(ExportError, match="no keyframe"):
        export_map(InMemoryMapStore(), "ply", tmp_path / "empty.ply")
    assert not (tmp_path / "empty.ply").exists()
