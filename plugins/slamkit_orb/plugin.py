"""Entry point of the slamkit_orb plugin: declares its components and their default config nodes."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="features",
            name="opencv_orb",
            target="slamkit_orb.opencv_orb.OpenCvOrbExtractor",
            config={
                "n_features": 1000,  # ORB-SLAM sec. VIII: 1000 features at 640x480
                "scale_factor": 1.2,  # ORB-SLAM sec. III-A: pyramid scale factor 1.2
                "n_levels": 8,  # ORB-SLAM sec. III-A: 8 pyramid levels
                "fast_threshold": 20,  # ORB-SLAM's initial FAST threshold (iniThFAST)
                "edge_threshold": 19,  # border without features, px (ORB-SLAM's EDGE_THRESHOLD)
            },
            description="OpenCV's cv2.ORB_create: the baseline extractor",
        )
    ]
