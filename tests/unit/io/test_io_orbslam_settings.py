"""ORB-SLAM2/3 settings reader on every ORB-SLAM2 example file, plus ORB-SLAM3-style files written here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import CalibrationError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.io.orbslam_settings import load_orbslam_settings

EXAMPLES = "calib/orb_slam2_examples"

# file -> (fx, fy, cx, cy, dist (k1, k2, p1, p2, k3), size or None, fps, bf, depth factor, nFeatures, iniThFAST)
EXPECTED = {
    "Monocular_EuRoC.yaml": (
        458.654,
        457.296,
        367.215,
        248.375,
        (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0),
        None,
        20.0,
        None,
        None,
        1000,
        20,
    ),
    "Monocular_KITTI04-12.yaml": (
        707.0912,
        707.0912,
        601.8873,
        183.1104,
        (0, 0, 0, 0, 0),
        None,
        10.0,
        None,
        None,
        2000,
        20,
    ),
    "Monocular_TUM1.yaml": (
        517.306408,
        516.469215,
        318.643040,
        255.313989,
        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
        None,
        30.0,
        None,
        None,
        1000,
        20,
    ),
    "RGB-D_TUM1.yaml": (
        517.306408,
        516.469215,
        318.643040,
        255.313989,
        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
        (640, 480),
        30.0,
        40.0,
        5000.0,
        1000,
        20,
    ),
    "RGB-D_TUM2.yaml": (
        520.908620,
        521.007327,
        325.141442,
        249.701764,
        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
        (640, 480),
        30.0,
        40.0,
        5208.0,
        1000,
        20,
    ),
    "RGB-D_TUM3.yaml": (535.4, 539.2, 320.1, 247.6, (0, 0, 0, 0, 0), (640, 480), 30.0, 40.0, 5000.0, 1000, 20),
    "Stereo_EuRoC.yaml": (
        435.2046959714599,
        435.2046959714599,
        367.4517211914062,
        252.2008514404297,
        (0, 0, 0, 0, 0),
        (752, 480),
        20.0,
        47.90639384423901,
        None,
        1200,
        20,
    ),
    "Stereo_KITTI04-12.yaml": (
        707.0912,
        707.0912,
        601.8873,
        183.1104,
        (0, 0, 0, 0, 0),
        (1241, 376),
        10.0,
        379.8145,
        None,
        2000,
        12,
    ),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_orbslam2_examples(shared_datasets: Path, name: str) -> None:
    fx, fy, cx, cy, dist, size, fps, bf, dmf, n_feat, ini_fast = EXPECTED[name]
    s = load_orbslam_settings(shared_datasets / EXAMPLES / name, image_size=(100, 50))
    assert isinstance(s.camera, PinholeCamera)
    np.testing.assert_allclose(s.camera.K, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=float), rtol=0, atol=0)
    np.testing.assert_allclose(s.camera.dist, dist, rtol=0, atol=0)
    assert (s.camera.width, s.camera.height) == (size or (100, 50))
    assert s.fps == fps and s.rgb_order is True
    assert s.bf == bf and s.depth_map_factor == dmf
    if bf is not None:
        assert s.baseline_m == pytest.approx(bf / fx)
    assert s.orb is not None
    assert (s.orb.n_features, s.orb.scale_factor, s.orb.n_levels, s.orb.ini_th_fast, s.orb.min_th_fast) == (
        n_feat,
        1.2,
        8,
        ini_fast,
        7,
    )
    assert (s.rectification is not None) == (name == "Stereo_EuRoC.yaml")


def test_stereo_euroc_rectification_blocks(shared_datasets: Path) -> None:
    s = load_orbslam_settings(shared_datasets / EXAMPLES / "Stereo_EuRoC.yaml")
    r = s.rectification
    assert r is not None and r.size == (752, 480)
    np.testing.assert_allclose(r.K_r, [[457.587, 0.0, 379.999], [0.0, 456.134, 255.238], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(r.D_l.ravel(), [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    np.testing.assert_allclose(r.R_l @ r.R_l.T, np.eye(3), atol=1e-9)
    assert r.baseline_m == pytest.approx(47.90639384423901 / 435.2046959714599)
    cam_r, T_l_r = s.stereo_pair()
    assert cam_r is s.camera and T_l_r[0, 3] == pytest.approx(0.110078, abs=1e-6)
    (lx, _), _ = r.maps()
    assert lx.shape == (480, 752) and lx.dtype == np.float32


def test_monocular_file_without_size_needs_image_size(shared_datasets: Path) -> None:
    with pytest.raises(CalibrationError, match=r"Monocular_TUM1\.yaml: .*lack Camera\.width/Camera\.height"):
        load_orbslam_settings(shared_datasets / EXAMPLES / "Monocular_TUM1.yaml")
    mono = load_orbslam_settings(shared_datasets / EXAMPLES / "Monocular_EuRoC.yaml", image_size=(752, 480))
    with pytest.raises(CalibrationError, match=r"stereo needs Camera\.bf"):
        mono.stereo_pair()


ORBSLAM3_FISHEYE = """%YAML:1.0
Camera.type: "KannalaBrandt8"
Camera.fx: 190.978477
Camera.fy: 190.973307
Camera.cx: 254.931706
Camera.cy: 256.897442
Camera.k1: 0.003482389402
Camera.k2: 0.000715034845
Camera.k3: -0.002053236141
Camera.k4: 0.000202936736
Camera2.fx: 190.442369
Camera2.fy: 190.434438
Camera2.cx: 252.597253
Camera2.cy: 254.917230
Camera2.k1: 0.003400600176
Camera2.k2: 0.001765284104
Camera2.k3: -0.002663488360
Camera2.k4: 0.000329780705
Camera.width: 512
Camera.height: 512
Camera.fps: 20.0
Camera.RGB: 1
Tlr: !!opencv-matrix
   rows: 3
   cols: 4
   dt: f
   data: [1.0, 0.0, 0.0, 0.101, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
Tbc: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [0.0, -1.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
ThDepth: 40.0
ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
"""


def test_orbslam3_fisheye_stereo(tmp_path: Path) -> None:
    p = tmp_path / "TUM_VI.yaml"
    p.write_text(ORBSLAM3_FISHEYE)
    s = load_orbslam_settings(p)
    assert isinstance(s.camera, KannalaBrandtCamera) and isinstance(s.camera_right, KannalaBrandtCamera)
    np.testing.assert_allclose(s.camera.k, [0.003482389402, 0.000715034845, -0.002053236141, 0.000202936736])
    assert s.camera_right.K[0, 0] == 190.442369
    assert s.T_l_r is not None and s.T_l_r.shape == (4, 4)
    assert s.T_l_r[0, 3] == pytest.approx(0.101)
    assert s.baseline_m == pytest.approx(0.101, abs=1e-6)
    assert s.T_b_c is not None and s.T_b_c[0, 1] == -1.0
    assert s.th_depth == 40.0


def test_orbslam3_v1_format(tmp_path: Path) -> None:
    text = """%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
Camera1.fx: 500.0
Camera1.fy: 501.0
Camera1.cx: 320.0
Camera1.cy: 240.0
Camera1.k1: 0.1
Camera1.k2: -0.2
Camera1.p1: 0.001
Camera1.p2: 0.002
Camera.width: 640
Camera.height: 480
Camera.fps: 30
Camera.RGB: 0
Stereo.b: 0.05
RGBD.DepthMapFactor: 1000.0
"""
    p = tmp_path / "v1.yaml"
    p.write_text(text)
    s = load_orbslam_settings(p)
    assert s.camera.K[1, 1] == 501.0
    assert isinstance(s.camera, PinholeCamera)
    np.testing.assert_allclose(s.camera.dist, np.array([0.1, -0.2, 0.001, 0.002, 0.0]))
    assert s.baseline_m == 0.05 and s.bf == pytest.approx(25.0)
    assert s.depth_map_factor == 1000.0 and s.rgb_order is False and s.orb is None


def test_malformed_settings(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("%YAML:1.0\nCamera.fx: 500.0\nCamera.fy: [1, 2\nCamera.cx: : 3\n")
    with pytest.raises(CalibrationError, match=r"bad\.yaml:\d+: .*cannot parse ORB-SLAM settings"):
        load_orbslam_settings(p)
    p.write_text(
        "%YAML:1.0\nCamera.fx: 500.0\nCamera.fy: 500.0\nCamera.cx: 320.0\nCamera.width: 640\nCamera.height: 480\n"
    )
    with pytest.raises(
        CalibrationError, match=r"bad\.yaml: ORB-SLAM settings lacks 'Camera\.cy' \(expected a number\)"
    ):
        load_orbslam_settings(p)
    p.write_text("%YAML:1.0\nCamera.fx: abc\nCamera.fy: 500.0\nCamera.cx: 320.0\nCamera.cy: 240.0\n")
    with pytest.raises(CalibrationError, match=r"bad\.yaml: 'Camera\.fx' should be a number"):
        load_orbslam_settings(p, image_size=(640, 480))
    p.write_text("%YAML:1.0\nCamera.fx: -5\nCamera.fy: 500.0\nCamera.cx: 320.0\nCamera.cy: 240.0\n")
    with pytest.raises(CalibrationError, match=r"bad\.yaml: Camera\.fx and Camera\.fy must be positive"):
        load_orbslam_settings(p, image_size=(640, 480))
    with pytest.raises(CalibrationError, match=r"ORB-SLAM settings: file .*none\.yaml does not exist"):
        load_orbslam_settings(tmp_path / "none.yaml")
