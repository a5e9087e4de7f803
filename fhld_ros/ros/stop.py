"""SIGINT and SIGTERM as a stop of lane_detector, raised as KeyboardInterrupt, or held.

Held while the node is imported and built: a KeyboardInterrupt raised inside an extension
module's initialisation can abort the process instead of stopping it (onnx's, imported by the
model export: pybind11 throws through a destructor, SIGABRT; seen in CI). Held signals are only
recorded; rclpy's own handler still shuts its context down at once, so whatever rclpy call
comes next fails, and the caller checks `received` when the held code is done.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

received: list[int] = []  # the signals received, held or not
_holding = [0]


def interrupt(signum: int, frame: object) -> None:
    """The signal handler lane_detector installs for SIGINT and SIGTERM."""
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
