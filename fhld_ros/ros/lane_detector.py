"""`lane_detector` (ros2 run fhld_ros lane_detector): the node, stoppable at any moment.

Importing the node takes seconds (torch, ONNX Runtime, rclpy), and a SIGINT or SIGTERM can come
during that, while rclpy is not yet listening: Ctrl-C would end in a KeyboardInterrupt traceback
and SIGTERM in the default kill. This module imports nothing heavy, turns both signals into
stops (ros/stop.py: held while the node is imported and built, KeyboardInterrupt after), and
only then imports the node, so every stop exits 0 without a traceback (node.main handles the
moments after rclpy.init, whose handlers take over then).
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
            from fhld_ros.ros import node  # here, not at the top: see the module docstring
        code = 0 if stop.received else node.main(args)
    except KeyboardInterrupt:
        code = 0
    except Exception:
        # a stop that made something fail on its way out (rcl's init, say): still the stop
        if not stop.received:
            raise
        code = 0
    if stop.received:
        # A KeyboardInterrupt that passed through Python run from C (pybind11's exec, inside
        # torch and rclpy) leaves CPython set to re-raise SIGINT on itself at exit, caught or
        # not (1 stop in 8 ended killed by SIGINT): leave now, the stop is complete.
        # A stop is a stop: exit 0 even where it made something fail (rcl's init, say).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return code


if __name__ == '__main__':
    sys.exit(main())
