"""End to end over real DDS (loopback profile): a simulated bag played to the running node.

The node runs as its own process with use_sim_time; `fhld play` publishes the bag with /clock;
this process listens to /lanes, the ego Paths and /diagnostics like a mapping stack would.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeOutputs, wait_until

from fhld_ros.bagio import read_messages
from msg_adapters.family import rclpy_family
from msg_adapters.lanes import DELETEALL, marker_array_to_lanes
from msg_adapters.pointcloud2 import create_cloud

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SWEEPS = 30
STARTUP_SWEEPS = 3
DETECTOR = 'classical'


@pytest.fixture(scope='module')
def scene(tmp_path_factory):
    """A short simulated drive and `fhld replay` of it (the reference output)."""
    root = tmp_path_factory.mktemp('e2e')
    sim, pred = root / 'sim', root / 'pred'
    for cmd in (['simulate', str(sim), '--seed', '11', '--sweeps', str(SWEEPS), '--quiet'],
                ['replay', str(sim), str(pred), '--detector', DETECTOR, '--quiet']):
        done = subprocess.run([sys.executable, '-m', 'fhld_ros.cli', *cmd], capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 0, done.stderr
    replayed = {marker_array_to_lanes(m).stamp_ns: marker_array_to_lanes(m)
                for _, _, m in read_messages(pred, ['/lanes'])}
    return sim, replayed


@pytest.fixture(scope='module')
def node_process(ros_env):
    node = subprocess.Popen(
        [sys.executable, '-m', 'fhld_ros.ros.lane_detector', '--ros-args',
         '-p', f'detector:={DETECTOR}', '-p', 'use_sim_time:=true'],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield node
    if node.poll() is None:
        node.kill()
    node.wait()


# DDS discovery at start-up on a loaded 2-core CI machine is a race the test cannot control;
# a rerun replays the bag to the same node (time goes back: the grid resets).
@pytest.mark.flaky(reruns=3)
def test_bag_played_to_the_node_gives_the_replay_lanes(scene, node_process, ros_env,
                                                       rclpy_context):
    sim, replayed = scene
    listener = NodeOutputs(rclpy_context, 'e2e_listener', depth=50)
    try:
        # subscriptions match while the node is still starting up; its first diagnostics
        # say it spins, so nothing published from now on waits in a full reader queue
        assert wait_until(lambda: len(listener.diagnostics) >= 1, 60), 'the node never came up'
        play = subprocess.run(
            [sys.executable, '-m', 'fhld_ros.cli', 'play', str(sim), '--wait-for', '/points',
             '/odom'],
            env=ros_env, capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stderr
        assert wait_until(lambda: len(listener.diagnostics) >= 1, 10)
        wait_until(lambda: int(listener.diagnostic_values().get('clouds', 0)) >= SWEEPS, 10)
        time.sleep(1.0)  # the last detection cycle
        assert node_process.poll() is None, 'the node died'
        values = listener.diagnostic_values()
        # Reliable input loses nothing once discovery has settled; on a loaded 2-core machine
        # the very first samples can still race the reader's side of the match (or their
        # odometry can), so the first STARTUP_SWEEPS are allowed to go missing, no others.
        assert int(values['clouds']) >= SWEEPS - STARTUP_SWEEPS, values
        assert int(values['clouds_received']) >= SWEEPS - STARTUP_SWEEPS, values
        assert len(listener.lanes) >= 3, f'only {len(listener.lanes)} /lanes messages'
        settled = min(replayed) + (STARTUP_SWEEPS + 10) * 100_000_000  # full 1 s of sweeps
        matched = 0
        for msg in listener.lanes:
            first, *rest = msg.markers
            assert first.action == DELETEALL and first.ns == 'lanes'
            assert rest[-1].ns == 'bev_window' and len(rest[-1].points) == 5
            assert all(m.ns == 'lanes' for m in rest[:-1])
            assert all(m.header.frame_id == 'odom' for m in msg.markers)
            got = marker_array_to_lanes(msg)
            if got.stamp_ns < settled:
                matched += 1
                continue
            reference = replayed.get(got.stamp_ns)
            assert reference is not None, f'no replay output at {got.stamp_ns}'
            np.testing.assert_allclose(got.window_outline, reference.window_outline, atol=1e-6)
            assert len(got.lanes) == len(reference.lanes)
            for a, b in zip(got.lanes, reference.lanes):
                np.testing.assert_allclose(a, b, atol=1e-4)
            matched += 1
        assert matched == len(listener.lanes)
        assert len(listener.left) == len(listener.right) == len(listener.lanes)
        assert any(len(p.poses) for p in listener.left), 'ego left lane never found'
        # ids are stable: consecutive frames share most of their ids
        ids = [set(marker_array_to_lanes(m).ids.tolist()) for m in listener.lanes]
        shared = [len(a & b) / max(len(b), 1) for a, b in zip(ids, ids[1:]) if b]
        assert np.mean(shared) > 0.6, ids
    finally:
        listener.close()


def test_bad_clouds_are_dropped_counted_and_the_node_lives(node_process, rclpy_context):
    family = rclpy_family()
    listener = NodeOutputs(rclpy_context, 'e2e_listener', depth=50)
    pub_node = rclpy.create_node('bad_cloud_publisher', context=rclpy_context)
    cloud_type = family.cls('sensor_msgs/msg/PointCloud2')
    pub = pub_node.create_publisher(cloud_type, 'points',
                                    QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    clock = pub_node.create_publisher(family.cls('rosgraph_msgs/msg/Clock'), '/clock', 10)
    try:
        assert wait_until(lambda: pub.get_subscription_count() > 0, 10)
        before = int(listener.diagnostic_values().get('bad_clouds', 0)) if wait_until(
            lambda: listener.diagnostics, 5) else 0
        stamp = 10_000_000_000_000
        points = np.zeros(100, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                      ('intensity', '<f4')])
        truncated = create_cloud(cloud_type, family.header(stamp, 'lidar'), points)
        truncated.data = truncated.data[:-16]
        fieldless = create_cloud(cloud_type, family.header(stamp, 'lidar'), points)
        fieldless.fields = []
        points['x'] = np.nan
        all_nan = create_cloud(cloud_type, family.header(stamp, 'lidar'), points)
        for msg in (truncated, fieldless, all_nan):
            clock.publish(family.new('rosgraph_msgs/msg/Clock', clock=family.stamp(stamp)))
            pub.publish(msg)
        def bad_clouds() -> int:
            return int(listener.diagnostic_values().get('bad_clouds', 0))
        assert wait_until(lambda: bad_clouds() >= before + 2, 10), listener.diagnostic_values()
        values = listener.diagnostic_values()
        assert 'PointCloud2' in values['last_error'] or 'odometry' in values['last_error']
        assert node_process.poll() is None, 'the node died on bad input'
        node_process.send_signal(signal.SIGINT)
        output, _ = node_process.communicate(timeout=20)
        assert node_process.returncode == 0, output
        assert 'Traceback' not in output, output
        assert 'dropped bad clouds' in output
    finally:
        pub_node.destroy_node()
        listener.close()
