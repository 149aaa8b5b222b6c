"""slamkit_orb: ORB feature extractors for slamkit (first-party plugin).

``features=opencv_orb`` is OpenCV's stock ORB, the baseline that ORB-SLAM's own extractor is measured
against.
"""
