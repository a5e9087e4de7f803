"""The camera as the annotation pipeline, the simulator and camera detectors see it: the
pinhole calibration (calibration.py), 2D lane labels (labels2d.py) and the camera topics of a
bag (camera_topics.py)."""
