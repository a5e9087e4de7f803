"""`camera_lane_detector` (ros2 run fhld_ros camera_lane_detector): the camera node, stoppable
at any moment, as lane_detector is (fhld_ros/ros/lane_detector.py says why: the heavy imports
come after SIGINT and SIGTERM are turned into stops, so every stop exits 0 without a traceback).
"""
from __future__ import annotations

import sys

from fhld_ros.ros import stop


def main(args: list[str] | None = None) -> int:
    return stop.main('fhld_ros.ros.camera_node', args)


if __name__ == '__main__':
    sys.exit(main())
