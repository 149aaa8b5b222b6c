"""slamkit_orb: ORB feature extractors for slamkit (first-party plugin).

``features=orb`` is ORB-SLAM's own extractor (orbslam_extractor.py); ``features=opencv_orb`` is OpenCV's
stock ORB, the baseline it is measured against (benchmarks/orb_extractor.py).
"""
