"""Helpers for tests that wait on DDS traffic, and for the tests that feed either node a bag
and compare its lane messages with the replay's."""
from __future__ import annotations

import pathlib
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from fhld_ros.bagio import read_raw
from fhld_ros.lane_output import LANE_TOPICS
from fhld_ros.ros.executor import spin


def wait_until(predicate: Callable[[], object], timeout: float, period: float = 0.05) -> bool:
    """Poll predicate until it is true or timeout seconds pass; its last value decides."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())


def stop(process: subprocess.Popen, timeout: float = 20) -> None:
    """A node process stopped as Ctrl-C's SIGTERM stops it; killed when it hangs."""
    if process.poll() is None:
        process.terminate()
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


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


class RawLaneOutputs:
    """A node's lane topics as serialized messages, in arrival order per topic, and its newest
    /diagnostics values. Subclasses add the input publishers, then call start()."""

    def __init__(self, context: rclpy.Context, name: str) -> None:
        self.qos = qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.node = rclpy.create_node(name, context=context)
        types = {'visualization_msgs/msg/MarkerArray': MarkerArray, 'nav_msgs/msg/Path': Path}
        self.got: dict[str, list[bytes]] = {suffix: [] for suffix in LANE_TOPICS}
        for suffix, type_name in LANE_TOPICS.items():
            self.node.create_subscription(types[type_name], 'lanes' + suffix,
                                          self.got[suffix].append, qos, raw=True)
        self.diagnostics: dict[str, str] = {}
        self.node.create_subscription(
            DiagnosticArray, 'diagnostics', lambda m: self.diagnostics.update(
                {kv.key: kv.value for kv in m.status[0].values}), qos)

    def start(self) -> None:
        self.executor, self.thread = spin_in_background(self.node)


def settled(node: rclpy.node.Node, probe: RawLaneOutputs) -> bool:
    """No detection due or running in `node`, and each of its detections' messages in."""
    with node.lock:
        due, detections = node.pipeline.detection_due, node.pipeline.counters['detections']
    return (not due and not node.detecting.locked()
            and all(len(got) == detections for got in probe.got.values()))


def feed(node: rclpy.node.Node, probe: RawLaneOutputs, bag: pathlib.Path,
         inputs: Mapping[str, tuple[object, int]],
         handled: Callable[[rclpy.node.Node], tuple[int, int]], settle_sec: float) -> None:
    """Publish the bag's `inputs` (topic -> (publisher, its place in `handled(node)`)) one
    message at a time: each waits until the node took the one before and its detections are
    out, so the node sees the bag at the replay's pace."""
    for topic, _, _, raw in read_raw(bag, list(inputs)):
        publisher, place = inputs[topic]
        expected = list(handled(node))
        expected[place] += 1
        publisher.publish(raw)
        assert wait_until(lambda want=tuple(expected): handled(node) == want, 20), \
            (topic, handled(node))
        assert wait_until(lambda: settled(node, probe), settle_sec), \
            'the detections never settled'


@contextmanager
def spinning(node: rclpy.node.Node, probe: RawLaneOutputs) -> Iterator[None]:
    """`node` spun as its main() spins it, beside `probe`; after, the context shuts down (a
    Ctrl-C's way) and both are destroyed."""
    spinner = threading.Thread(target=spin, args=(node,), daemon=True)
    spinner.start()
    try:
        yield
    finally:
        node.context.try_shutdown()
        spinner.join(timeout=20)
        probe.thread.join(timeout=20)
        node.destroy_node()
        probe.node.destroy_node()
