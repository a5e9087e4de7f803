"""Helpers for tests that wait on DDS traffic."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray


def wait_until(predicate: Callable[[], object], timeout: float, period: float = 0.05) -> bool:
    """Poll predicate until it is true or timeout seconds pass; its last value decides."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())


def spin_in_background(node: rclpy.node.Node) -> tuple[SingleThreadedExecutor, threading.Thread]:
    """Spin node in a daemon thread until its context shuts down (the end of the test)."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    return executor, thread


class NodeOutputs:
    """The lane_detector's outputs (/lanes, the ego Paths, /diagnostics) as a user's node sees
    them: plain rclpy subscriptions, spun by an executor in a background thread."""

    def __init__(self, context: rclpy.Context, name: str, depth: int = 20) -> None:
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.node = rclpy.create_node(name, context=context)
        self.lanes, self.left, self.right, self.diagnostics = [], [], [], []
        self.node.create_subscription(MarkerArray, 'lanes', self.lanes.append, qos)
        self.node.create_subscription(Path, 'lanes/ego_left', self.left.append, qos)
        self.node.create_subscription(Path, 'lanes/ego_right', self.right.append, qos)
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self.diagnostics.append,
                                      qos)
        self.executor, self.thread = spin_in_background(self.node)

    def diagnostic_values(self) -> dict[str, str]:
        """Key -> value of the newest /diagnostics status ({} before the first)."""
        if not self.diagnostics:
            return {}
        return {kv.key: kv.value for kv in self.diagnostics[-1].status[0].values}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
