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
        ),
        ComponentSpec(
            kind="features",
            name="orb",
            target="slamkit_orb.orbslam_extractor.OrbSlamExtractor",
            config={
                # ORB-SLAM sec. VIII: 1000 features at 640x480; KITTI (1241x376) uses 2000 (set by its config)
                "n_features": 1000,
                "scale_factor": 1.2,  # ORB-SLAM sec. III-A: pyramid scale factor 1.2
                "n_levels": 8,  # ORB-SLAM sec. III-A: 8 pyramid levels
                "ini_fast_threshold": 20,  # ORB-SLAM's iniThFAST (ORBextractor.iniThFAST in its settings)
                "min_fast_threshold": 7,  # ORB-SLAM's minThFAST: fallback in cells where 20 finds nothing
                "cell_size_px": 30,  # ORB-SLAM code: grid cell side W = 30 in ComputeKeyPointsOctTree
                "edge_threshold": 19,  # ORB-SLAM code: EDGE_THRESHOLD, border without features, px
                "patch_size": 31,  # ORB-SLAM code: PATCH_SIZE, side of the rBRIEF patch, px
                "half_patch_size": 15,  # ORB-SLAM code: HALF_PATCH_SIZE, radius of the orientation patch, px
                "n_threads": 2,  # slamkit: threads the pyramid levels are shared among (output unchanged)
                # slamkit: FAST implementation, "compiled" (numba, fast9.py: ~7x faster than OpenCV + KeyPoint
                # objects, GIL released) or "opencv" (cv2.FastFeatureDetector); identical corners either way
                "fast_backend": "compiled",
            },
            description="ORB-SLAM's extractor: grid FAST with fallback threshold, quadtree spread, rBRIEF",
        ),
    ]
