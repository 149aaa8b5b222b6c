"""Entry point of the slamkit_orb plugin: declares its components and their default config nodes."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


def _from_dataset(key: str, default: float) -> str:
    """A config value taken from the dataset's ORB-SLAM extractor settings (``dataset.orb_extractor.KEY``), else
    ``default``. The app replaces it by the settings file's ``ORBextractor.*`` when the dataset has one; a value set
    on the command line replaces the interpolation and wins (slamkit.app.camera_feature_settings)."""
    return f"${{oc.select:dataset.orb_extractor.{key},{default}}}"


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="features",
            name="opencv_orb",
            target="slamkit_orb.opencv_orb.OpenCvOrbExtractor",
            config={
                # camera-dependent: the dataset's ORB-SLAM settings (dataset.orb_extractor or its settings
                # file) unless set on the command line; else these defaults (docs/configs.md)
                "n_features": _from_dataset("n_features", 1000),  # ORB-SLAM sec. VIII: 1000 features at 640x480
                "scale_factor": _from_dataset("scale_factor", 1.2),  # ORB-SLAM sec. III-A: pyramid scale factor 1.2
                "n_levels": _from_dataset("n_levels", 8),  # ORB-SLAM sec. III-A: 8 pyramid levels
                "fast_threshold": _from_dataset("ini_th_fast", 20),  # ORB-SLAM's initial FAST threshold (iniThFAST)
                "edge_threshold": 19,  # border without features, px (ORB-SLAM's EDGE_THRESHOLD)
            },
            description="OpenCV's cv2.ORB_create: the baseline extractor",
        ),
        ComponentSpec(
            kind="features",
            name="orb",
            target="slamkit_orb.orbslam_extractor.OrbSlamExtractor",
            config={
                # camera-dependent: the dataset's ORB-SLAM settings (dataset.orb_extractor, e.g. KITTI's 2000
                # features at 1241x376, or its settings file's ORBextractor.*) unless set on the command line;
                # else these defaults (docs/configs.md, "Camera settings per dataset")
                "n_features": _from_dataset("n_features", 1000),  # ORB-SLAM sec. VIII: 1000 features at 640x480
                "scale_factor": _from_dataset("scale_factor", 1.2),  # ORB-SLAM sec. III-A: pyramid scale factor 1.2
                "n_levels": _from_dataset("n_levels", 8),  # ORB-SLAM sec. III-A: 8 pyramid levels
                # ORB-SLAM's iniThFAST (ORBextractor.iniThFAST in its settings)
                "ini_fast_threshold": _from_dataset("ini_th_fast", 20),
                # ORB-SLAM's minThFAST: fallback in cells where iniThFAST finds nothing
                "min_fast_threshold": _from_dataset("min_th_fast", 7),
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
