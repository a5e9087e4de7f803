"""FHLD detector (Guan et al., AAAI 2023): backbone, global curves, dynamic anchors, local
segments, and beside them the Hungarian matcher and the criterion that train it.

detector.py holds the entry points (FhldDetector, Detections); config.py the coordinate
conventions; checkpoint.py the weights on disk; inference.py the serving runtimes.
"""
