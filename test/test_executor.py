"""HandoffExecutor: still a MultiThreadedExecutor (concurrent callback groups, errors surface)."""
from __future__ import annotations

import threading
import time

import pytest
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_msgs.msg import String

from fhld_ros.ros.executor import HandoffExecutor

pytestmark = pytest.mark.ros


def test_callbacks_in_other_groups_run_while_one_blocks(ros_env, rclpy_context):
    """A timer callback waits for a subscription callback: needs two workers at once."""
    node = rclpy.create_node('handoff_probe', context=rclpy_context)
    received = threading.Event()
    outcome: list[bool] = []

    def blocking_timer() -> None:
        if not outcome:
            outcome.append(received.wait(timeout=20.0))

    node.create_timer(0.01, blocking_timer, callback_group=MutuallyExclusiveCallbackGroup())
    node.create_subscription(String, 'handoff', lambda _: received.set(), 10,
                             callback_group=MutuallyExclusiveCallbackGroup())
    publisher = node.create_publisher(String, 'handoff', 10)
    executor = HandoffExecutor(num_threads=3, context=rclpy_context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        deadline = time.monotonic() + 20
        while not outcome and time.monotonic() < deadline:
            publisher.publish(String(data='x'))
            time.sleep(0.05)
    finally:
        executor.shutdown()
        spinner.join(timeout=10)
        node.destroy_node()
    assert outcome == [True], 'the subscription callback never ran beside the blocked timer'


def test_callback_errors_surface_from_spin(ros_env, rclpy_context):
    node = rclpy.create_node('handoff_errors', context=rclpy_context)

    def failing() -> None:
        raise RuntimeError('callback failed')

    node.create_timer(0.01, failing)
    executor = HandoffExecutor(num_threads=2, context=rclpy_context)
    executor.add_node(node)
    try:
        with pytest.raises(RuntimeError, match='callback failed'):
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
