"""`lane_detector` (ros2 run fhld_ros lane_detector): the node, stoppable at any moment.

Importing the node takes seconds (torch, ONNX Runtime, rclpy), and a SIGINT or SIGTERM can come
during that, while rclpy is not yet listening: Ctrl-C would end in a KeyboardInterrupt traceback
and SIGTERM in the default kill. This module imports nothing heavy; stop.main turns both signals
into stops (ros/stop.py: held while the node is imported and built, KeyboardInterrupt after),
and only then imports the node, so every stop exits 0 without a traceback (node.main handles
the moments after rclpy.init, whose handlers take over then).
"""
from __future__ import annotations

import sys

from fhld_ros.ros import stop


def main(args: list[str] | None = None) -> int:
    return stop.main('fhld_ros.ros.node', args)


if __name__ == '__main__':
    sys.exit(main())
