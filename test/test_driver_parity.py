"""The node and `fhld replay` are thin drivers of one LanePipeline: on one bag they publish the
same messages, byte for byte.

The bag is a user's recording, not our simulator's order: odometry at half the sweep rate,
recorded after the sweep of its stamp (so sweeps wait for it and go in two at a time), one
malformed cloud and one odometry message with a broken quaternion. The node runs over real DDS
(loopback) and is fed one message at a time, each once it has handled the last, so that it
computes what a replay computes; its live-only paths (poses extrapolated past odometry DDS
lost, the wall-clock wait) are set out of reach.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from ros_helpers import RawLaneOutputs, feed, spinning, wait_until
from sensor_msgs.msg import PointCloud2

from fhld_ros.bagio import BagWriter, read_raw
from fhld_ros.commands.replay import replay
from fhld_ros.lane_output import LANE_TOPICS
from fhld_ros.parameters import DetectorParams
from fhld_ros.ros.node import LaneDetectorNode
from msg_adapters.family import rosbags_family

pytestmark = [pytest.mark.ros]

SWEEPS = 16
MALFORMED_SWEEP = 5
BAD_POSE_AFTER_SWEEP = 9
PARAMS = {'detector': 'classical', 'odom_extrapolate_sec': 0.0, 'odom_wait_sec': 5.0}


def _user_bag(sim: Path, out: Path) -> None:
    """The simulated drive re-recorded as described in the module doc."""
    family = rosbags_family()
    store = family.typestore
    clouds = list(read_raw(sim, ['/points']))
    poses = {stamp: (msgtype, raw) for _, msgtype, stamp, raw in read_raw(sim, ['/odom'])}
    with BagWriter(out) as writer:
        for k, (topic, msgtype, stamp, raw) in enumerate(clouds):
            if k == MALFORMED_SWEEP:
                cloud = store.deserialize_cdr(raw, msgtype)
                cloud.data = cloud.data[:-7]  # not a whole number of points
                writer.write(topic, msgtype, stamp, cloud)
            else:
                writer.write(topic, msgtype, stamp, raw)
            if k % 2 == 0 or k == len(clouds) - 1:
                odom_type, pose = poses[stamp]
                writer.write('/odom', odom_type, stamp + 1, pose)
            if k == BAD_POSE_AFTER_SWEEP:
                odom_type, pose = poses[stamp]
                broken = store.deserialize_cdr(pose, odom_type)
                broken.pose.pose.orientation.w = 0.0
                broken.pose.pose.orientation.z = 0.0
                writer.write('/odom', odom_type, stamp + 2, broken)


@pytest.fixture(scope='module')
def user_bag(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp('parity')
    done = subprocess.run([sys.executable, '-m', 'fhld_ros.cli', 'simulate', str(root / 'sim'),
                           '--seed', '4', '--sweeps', str(SWEEPS), '--quiet'],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    _user_bag(root / 'sim', root / 'user')
    return root / 'user'


class RawOutputs(RawLaneOutputs):
    """The node's lane topics as serialized messages, in arrival order per topic."""

    def __init__(self, context: rclpy.Context) -> None:
        super().__init__(context, 'parity_probe')
        self.points = self.node.create_publisher(PointCloud2, 'points', self.qos)
        self.odom = self.node.create_publisher(Odometry, 'odom', self.qos)
        self.start()


def _handled(node: LaneDetectorNode) -> tuple[int, int]:
    """(clouds, odometry messages) the node's pipeline has taken, dropped ones included."""
    with node.lock:
        c = node.pipeline.counters
        return (c['clouds'] + c['bad_clouds'] + len(node.pipeline.waiting_stamps),
                c['odometry'] + c['bad_odometry'])


def test_node_and_replay_publish_the_same_messages(user_bag, tmp_path, rclpy_context):
    stats = replay(user_bag, tmp_path / 'replayed', DetectorParams(**PARAMS), progress=False)
    assert stats['dropped'] == 1 and stats['bad_odometry'] == 1
    replayed = {suffix: [raw for *_, raw in read_raw(tmp_path / 'replayed', ['/lanes' + suffix])]
                for suffix in LANE_TOPICS}
    assert len(replayed['']) >= SWEEPS - 3, 'the replay detected too few sweeps'

    node = LaneDetectorNode(context=rclpy_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in PARAMS.items()])
    probe = RawOutputs(rclpy_context)
    with spinning(node, probe):
        assert wait_until(lambda: probe.points.get_subscription_count() >= 1
                          and probe.odom.get_subscription_count() >= 2
                          and all(node.count_subscribers(node.params.lanes_topic + suffix) >= 1
                                  for suffix in LANE_TOPICS), 30), 'discovery never completed'
        feed(node, probe, user_bag, {'/points': (probe.points, 0), '/odom': (probe.odom, 1)},
             _handled, 20)
        # the end of the bag: what still waits for odometry goes in as a replay lets it in
        with node.lock:
            assert node.pipeline.waiting_stamps == []
        for suffix in LANE_TOPICS:
            assert probe.got[suffix] == replayed[suffix], f'/lanes{suffix} differs'
        assert node.pipeline.counters['bad_clouds'] == 1
        assert node.pipeline.counters['bad_odometry'] == 1
        assert node.pipeline.counters['sweeps_skipped'] == 0  # fed at its pace: none overtaken
