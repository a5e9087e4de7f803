"""LaneDetectorNode in-process: clouds and odometry in, /lanes, ego Paths and /diagnostics out.

The node (shipped FHLD weights) and a probe node share one rclpy context; the node spins as
lane_detector's main() spins it, and stops the way Ctrl-C stops it: the context shuts down.
"""
from __future__ import annotations

import dataclasses
import re
import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeOutputs, wait_until
from sensor_msgs.msg import PointCloud2

from fhld_ros.dataclass_dict import field_docs, to_plain
from fhld_ros.errors import ConfigError
from fhld_ros.parameters import DetectorParams
from fhld_ros.ros import diagnostics
from fhld_ros.ros.diagnostics import STAGES
from fhld_ros.ros.executor import spin
from fhld_ros.ros.node import LaneDetectorNode
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


@pytest.fixture
def no_latency_or_stale_levels(monkeypatch):
    """Nodes started after this judge only drops and errors: a test of lanes and values
    cannot fail because a loaded machine was slow (test/test_diagnostics.py has the levels)."""
    monkeypatch.setattr(diagnostics, 'THRESHOLDS', dataclasses.replace(
        diagnostics.THRESHOLDS, latency_p95_warn_ms=1e9, latency_p95_error_ms=1e9,
        stale_warn_sec=1e9, stale_error_sec=1e9))


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
    """Sweeps 0.1 s apart, each once the last one's /lanes is out: on a loaded machine a
    detection can take longer than a sweep period, and the node then rightly reports the sweep
    it skipped (a WARN level), which is not what these tests check (test_diagnostics.py is)."""
    family = rclpy_family()
    stamps = []
    for k, sweep in enumerate(sweeps):
        stamp = START_NS + k * 100_000_000
        sent = time.monotonic()
        probe.odom.publish(make_odometry(family, family.header(stamp, 'odom'), 'lidar',
                                         sweep.sensor_to_odom))
        probe.points.publish(create_cloud(PointCloud2, family.header(stamp, 'lidar'),
                                          sweep.points, height=sweep.height))
        stamps.append(stamp)
        assert wait_until(lambda stamp=stamp: stamp in {marker_array_to_lanes(m).stamp_ns
                                                        for m in list(probe.lanes)}, 30), k
        time.sleep(max(0.0, 0.1 - (time.monotonic() - sent)))
    return stamps


def test_node_detects_lanes_and_reports_diagnostics(running, sweeps, one_torch_thread,
                                                    no_latency_or_stale_levels):
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
        assert descriptor.read_only, name
        assert node.get_parameter(name).value == plain[name], name


def test_parameter_changes_at_run_time_are_refused_with_a_reason(running):
    """The node reads its parameters once: `ros2 param set` must fail, not silently do
    nothing (it used to succeed and change nothing)."""
    node, _ = running(detector='classical')
    results = node.set_parameters([Parameter('score_threshold', value=0.9),
                                   Parameter('points_topic', value='other')])
    assert [r.successful for r in results] == [False, False]
    assert results[0].reason == 'Trying to set a read-only parameter: score_threshold.'
    default = DetectorParams().score_threshold
    assert node.get_parameter('score_threshold').value == default != 0.9
    assert node.params.score_threshold == default
    # use_sim_time is rclpy's own and applied live: still settable
    assert node.set_parameters([Parameter('use_sim_time', value=True)])[0].successful


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
    with pytest.raises(ConfigError, match="detector must be 'fhld' or 'classical'"):
        LaneDetectorNode(context=rclpy_context,
                         parameter_overrides=[Parameter('detector', value='deep')])
    with pytest.raises(ConfigError, match='^rate_hz must be a number with a decimal point'):
        LaneDetectorNode(context=rclpy_context,
                         parameter_overrides=[Parameter('rate_hz', value='fast')])


def _small_cloud(stamp_ns: int, rng: np.random.Generator) -> PointCloud2:
    points = np.zeros(500, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                  ('intensity', '<f4')])
    points['x'], points['y'] = rng.uniform(-10, 10, (2, 500))
    points['z'], points['intensity'] = -1.8, rng.uniform(0, 1, 500)
    return create_cloud(PointCloud2, rclpy_family().header(stamp_ns, 'lidar'), points)


def test_one_bad_cloud_warns_and_good_traffic_returns_to_ok(running, monkeypatch):
    # latency is not what this test is about: a loaded machine must not fail it
    monkeypatch.setattr(diagnostics, 'THRESHOLDS', dataclasses.replace(
        diagnostics.THRESHOLDS, latency_p95_warn_ms=1e9, latency_p95_error_ms=1e9))
    node, probe = running(detector='classical', size_px=128, resolution_m=0.2)
    assert wait_until(lambda: probe.points.get_subscription_count() > 0, 10)
    rng = np.random.default_rng(3)
    stop = threading.Event()

    def publish_good() -> None:  # 5 Hz: a detection would need 200 ms to overtake a sweep
        k = 0
        while not stop.is_set():
            probe.points.publish(_small_cloud(START_NS + k * 200_000_000, rng))
            k += 1
            stop.wait(0.2)
    publisher = threading.Thread(target=publish_good, daemon=True)
    publisher.start()
    try:
        def level_message() -> tuple:
            status = probe.diagnostics[-1].status[0] if probe.diagnostics else None
            return (status.level, status.message) if status else (None, '')
        assert wait_until(lambda: level_message() == (DiagnosticStatus.OK, 'running'), 15), (
            level_message())
        truncated = _small_cloud(START_NS - 1, rng)
        truncated.data = truncated.data[:-16]
        probe.points.publish(truncated)
        assert wait_until(lambda: probe.diagnostic_values().get('bad_clouds') == '1', 10)
        level, message = level_message()
        assert level == DiagnosticStatus.WARN, message
        assert re.fullmatch(r'dropped 1 of \d+ clouds in [\d.]+ s \(1 bad; \d+% > 0%\)',
                            message), message
        assert probe.diagnostic_values()['last_error'].startswith('bad_clouds: ')
        # once the bad cloud is older than the window, the level is OK again
        window = diagnostics.THRESHOLDS.window_sec
        assert wait_until(lambda: level_message() == (DiagnosticStatus.OK, 'running'),
                          window + 8), level_message()
        values = probe.diagnostic_values()
        assert values['bad_clouds'] == '1' and values['window_clouds_dropped'] == '0'
        assert values['last_error'].startswith('bad_clouds: ')  # kept, as information
    finally:
        stop.set()
        publisher.join(timeout=5)
