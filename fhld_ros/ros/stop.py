"""SIGINT and SIGTERM as a stop of a node (lane_detector, camera_lane_detector), raised as
KeyboardInterrupt, or held.

Held while the node is imported and built: a KeyboardInterrupt raised inside an extension
module's initialisation can abort the process instead of stopping it (onnx's, imported by the
model export: pybind11 throws through a destructor, SIGABRT; seen in CI). Held signals are only
recorded; rclpy's own handler still shuts its context down at once, so whatever rclpy call
comes next fails, and the caller checks `received` when the held code is done.

main() is both nodes' entry point around that; this module imports nothing heavy (see
fhld_ros/ros/lane_detector.py).
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

received: list[int] = []  # the signals received, held or not
_holding = [0]


def interrupt(signum: int, frame: object) -> None:
    """The signal handler main() installs for SIGINT and SIGTERM."""
    received.append(signum)
    if not _holding[0]:
        raise KeyboardInterrupt


@contextmanager
def held() -> Iterator[None]:
    """Signals inside are only recorded (see the module doc)."""
    _holding[0] += 1
    try:
        yield
    finally:
        _holding[0] -= 1


def main(node_module: str, args: list[str] | None = None) -> int:
    """Turn SIGINT and SIGTERM into stops, then import `node_module` (held) and run its main():
    every stop exits 0 without a traceback."""
    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    try:
        with held():
            node = importlib.import_module(node_module)  # heavy: torch, rclpy, the model
        code = 0 if received else node.main(args)
    except KeyboardInterrupt:
        code = 0
    except Exception:
        # a stop that made something fail on its way out (rcl's init, say): still the stop
        if not received:
            raise
        code = 0
    if received:
        # A KeyboardInterrupt that passed through Python run from C (pybind11's exec, inside
        # torch and rclpy) leaves CPython set to re-raise SIGINT on itself at exit, caught or
        # not (1 stop in 8 ended killed by SIGINT): leave now, the stop is complete.
        # A stop is a stop: exit 0 even where it made something fail (rcl's init, say).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return code
