"""`camera_lane_detector` (ros2 run fhld_ros camera_lane_detector): the camera node, stoppable
at any moment, as lane_detector is (fhld_ros/ros/lane_detector.py says why: the heavy imports
come after SIGINT and SIGTERM are turned into stops, so every stop exits 0 without a traceback).
"""
from __future__ import annotations

import os
import signal
import sys

from fhld_ros.ros import stop


def main(args: list[str] | None = None) -> int:
    signal.signal(signal.SIGINT, stop.interrupt)
    signal.signal(signal.SIGTERM, stop.interrupt)
    try:
        with stop.held():
            from fhld_ros.ros import camera_node  # here, not at the top: see the module doc
        code = 0 if stop.received else camera_node.main(args)
    except KeyboardInterrupt:
        code = 0
    except Exception:
        if not stop.received:  # a stop that made something fail on its way out: still a stop
            raise
        code = 0
    if stop.received:
        # as lane_detector: CPython may re-raise SIGINT on itself at exit; the stop is complete
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return code


if __name__ == '__main__':
    sys.exit(main())
