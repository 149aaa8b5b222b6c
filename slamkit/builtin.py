"""The core's own components (dataset readers, front ends, the in-memory map store), registered through the
``slamkit`` entry-point group exactly like any plugin. Their config nodes are YAML files in ``conf/dataset/``,
``conf/frontend/`` and ``conf/map/``."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            "dataset",
            "synthetic",
            "slamkit.io.synthetic.dataset.SyntheticDataset",
            description="slamkit's own rendered world with exact ground truth (the default)",
        ),
        ComponentSpec(
            "dataset",
            "tum_rgbd",
            "slamkit.io.tum_rgbd.TumRgbdDataset",
            description="TUM RGB-D sequence folder (rgb, depth, groundtruth)",
        ),
        ComponentSpec(
            "dataset",
            "euroc",
            "slamkit.io.euroc.EurocDataset",
            description="EuRoC/ASL folder (mav0: cam0, cam1, imu0, ground truth)",
        ),
        ComponentSpec(
            "dataset",
            "kitti",
            "slamkit.io.kitti.KittiDataset",
            description="KITTI odometry (sequences/NN, poses/NN.txt)",
        ),
        ComponentSpec(
            "dataset",
            "folder",
            "slamkit.io.folder.FolderDataset",
            description="a folder of images with a camera from config",
        ),
        ComponentSpec(
            "dataset", "video", "slamkit.io.video.VideoDataset", description="a video file with a camera from config"
        ),
        ComponentSpec(
            "dataset",
            "camera",
            "slamkit.io.camera.CameraDataset",
            description="a live camera or stream (device index or URL) through OpenCV, played in real time",
        ),
        ComponentSpec(
            "frontend",
            "mono",
            "slamkit.frontend.mono.MonocularFrontEnd",
            description="monocular: ORB features, their bearings from the camera model, no depth",
        ),
        ComponentSpec(
            "frontend",
            "rgbd",
            "slamkit.frontend.rgbd.RgbdFrontEnd",
            description="RGB-D: ORB features, depth from the registered depth map, virtual right u = u - bf / depth",
        ),
        ComponentSpec(
            "frontend",
            "stereo",
            "slamkit.frontend.stereo.StereoFrontEnd",
            description="rectified stereo: ORB in both images, ORB-SLAM2's row search, SAD refinement, depth = bf / d",
        ),
        ComponentSpec(
            "frontend",
            "stereo_rig",
            "slamkit.frontend.stereo_rig.StereoRigFrontEnd",
            description="non-rectified stereo (ORB-SLAM3): two cameras' keypoints as they are, matches by triangulation",
        ),
        ComponentSpec(
            "map",
            "memory",
            "slamkit.map.store.InMemoryMapStore",
            description="the map's entities and graphs in memory behind one readers-writer lock (the default)",
        ),
    ]
