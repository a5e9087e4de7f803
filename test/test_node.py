"""LaneDetectorNode in-process: clouds and odometry in, /lanes, ego Paths and /diagnostics out.

The node (shipped FHLD weights) and a probe node share one rclpy context; the node spins as
lane_detector's main() spins it, and stops the way Ctrl-C stops it: the context shuts down.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeOutputs, wait_until
from sensor_msgs.msg import PointCloud2

from fhld_ros.dataclass_dict import field_docs, to_plain
from fhld_ros.ros.diagnostics import STAGES
from fhld_ros.ros.node import LaneDetectorNode, spin
from fhld_ros.ros.parameters import DetectorParams
from fhld_ros.sim.simulator import Simulator
from msg_adapters.family import rclpy_family
from msg_adapters.lanes import DELETEALL, marker_array_to_lanes
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

pytestmark = pytest.mark.ros

SWEEPS = 6
START_NS = 1_700_000_000_000_000_000
RELIABLE = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)


class Probe(NodeOutputs):
    """Publishes clouds and odometry, collects the node's outputs; spins in its own thread."""

    def __init__(self, context) -> None:
        super().__init__(context, 'node_probe')
        self.points = self.node.create_publisher(PointCloud2, 'points', RELIABLE)
        self.odom = self.node.create_publisher(Odometry, 'odom', RELIABLE)


@pytest.fixture(scope='module')
def sweeps():
    sim = Simulator(seed=5, sweeps=SWEEPS, sensor='os1-64', road='highway', speed=20.0)
    return [sim.sweep(k) for k in range(SWEEPS)]


@pytest.fixture
def running(rclpy_context):
    """Start (node factory) -> (node, probe), spinning; stopped by a context shutdown after."""
    started = []

    def start(**overrides):
        node = LaneDetectorNode(context=rclpy_context, parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()])
        spinner = threading.Thread(target=spin, args=(node,), daemon=True)
        spinner.start()
        probe = Probe(rclpy_context)
        started.append((node, spinner, probe))
        return node, probe

    yield start
    rclpy_context.try_shutdown()  # what SIGINT does in main()
    for node, spinner, probe in started:
        spinner.join(timeout=20)
        probe.thread.join(timeout=20)
        assert not spinner.is_alive(), 'spin() did not return after the context shut down'
        node.destroy_node()  # spin() joined its workers: nothing runs in the node now
        probe.node.destroy_node()


def _publish(probe: Probe, sweeps) -> list[int]:
    family = rclpy_family()
    stamps = []
    for k, sweep in enumerate(sweeps):
        stamp = START_NS + k * 100_000_000
        probe.odom.publish(make_odometry(family, family.header(stamp, 'odom'), 'lidar',
                                         sweep.sensor_to_odom))
        probe.points.publish(create_cloud(PointCloud2, family.header(stamp, 'lidar'),
                                          sweep.points, height=sweep.height))
        stamps.append(stamp)
        time.sleep(0.1)
    return stamps


def test_node_detects_lanes_and_reports_diagnostics(running, sweeps, one_torch_thread):
    node, probe = running(model_threads=1)
    assert node.params == DetectorParams(model_threads=1)
    assert wait_until(lambda: probe.points.get_subscription_count() > 0
                 and probe.odom.get_subscription_count() > 0, 10)
    stamps = _publish(probe, sweeps)
    assert wait_until(lambda: int(probe.diagnostic_values().get('clouds', 0)) == SWEEPS
                 and probe.lanes and stamps[-1] in {
                     marker_array_to_lanes(m).stamp_ns for m in probe.lanes}, 30), (
        probe.diagnostic_values(), len(probe.lanes))
    for msg in probe.lanes:  # the /lanes contract (docs/design.md §3)
        first, *rest = msg.markers
        assert first.action == DELETEALL and first.ns == 'lanes'
        assert rest[-1].ns == 'bev_window' and len(rest[-1].points) == 5
        assert all(m.ns == 'lanes' for m in rest[:-1])
        assert all(m.header.frame_id == 'odom' for m in msg.markers)
        assert marker_array_to_lanes(msg).stamp_ns in stamps
    assert max(len(marker_array_to_lanes(m).lanes) for m in probe.lanes) >= 2
    assert wait_until(lambda: len(probe.left) == len(probe.right) == len(probe.lanes), 5)

    assert wait_until(lambda: 'latency_ms_p50' in probe.diagnostic_values(), 5)
    status = probe.diagnostics[-1].status[0]
    assert (status.name, status.level, status.message) == (
        'fhld_ros: lane_detector', DiagnosticStatus.OK, 'running')
    values = probe.diagnostic_values()
    assert int(values['clouds_received']) == SWEEPS
    assert 1 <= int(values['detections']) <= SWEEPS
    assert {f'stage_{name}_ms_p50' for name in STAGES} <= set(values)
    assert float(values['latency_ms_p95']) >= float(values['latency_ms_p50']) > 0
    assert (values['input_reliability'], values['last_error']) == ('RELIABLE', '')


def test_parameters_are_declared_with_their_descriptions(running):
    node, _ = running(detector='classical', rate_hz=5.0)
    docs = field_docs(DetectorParams)
    plain = to_plain(DetectorParams(detector='classical', rate_hz=5.0))
    for name, descriptor in zip(docs, node.describe_parameters(list(docs))):
        assert descriptor.description == docs[name], name
        assert node.get_parameter(name).value == plain[name], name


def test_auto_reliability_follows_a_best_effort_publisher(running):
    node, probe = running(detector='classical')
    assert wait_until(lambda: 'input_reliability' in probe.diagnostic_values(), 10)
    assert probe.diagnostic_values()['input_reliability'] == 'RELIABLE'
    driver = probe.node.create_publisher(
        PointCloud2, 'points', QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
    assert wait_until(lambda: node.points_reliability == ReliabilityPolicy.BEST_EFFORT, 10)
    assert wait_until(lambda: driver.get_subscription_count() == 1, 10)
    assert wait_until(lambda: probe.diagnostic_values()['input_reliability'] == 'BEST_EFFORT', 5)


def test_bad_parameters_are_refused_before_anything_starts(rclpy_context):
    with pytest.raises(ValueError, match="detector must be 'fhld' or 'classical'"):
        LaneDetectorNode(context=rclpy_context,
                         parameter_overrides=[Parameter('detector', value='deep')])
    with pytest.raises(ParameterException, match='rate_hz'):
        LaneDetectorNode(context=rclpy_context,
                         parameter_overrides=[Parameter('rate_hz', value='fast')])


def test_bad_clouds_are_dropped_and_counted(running):
    node, probe = running(detector='classical')
    assert wait_until(lambda: probe.points.get_subscription_count() > 0, 10)
    family = rclpy_family()
    points = np.zeros(100, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                  ('intensity', '<f4')])
    truncated = create_cloud(PointCloud2, family.header(START_NS, 'lidar'), points)
    truncated.data = truncated.data[:-16]
    probe.points.publish(truncated)
    assert wait_until(lambda: probe.diagnostic_values().get('bad_clouds') == '1', 10), (
        probe.diagnostic_values())
    status = probe.diagnostics[-1].status[0]
    assert (status.level, status.message) == (DiagnosticStatus.WARN, '1 bad messages dropped')
    assert probe.diagnostic_values()['last_error'].startswith('bad_clouds: ')
