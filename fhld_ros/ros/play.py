"""`fhld play BAG`: publish a bag over DDS in real time with /clock (a `ros2 bag play` stand-in).

Messages go out as their recorded CDR bytes (no decode/encode), each preceded by /clock at its
log time, so nodes run with use_sim_time:=true follow the bag's time. DDS stays on loopback
unless the caller's environment says otherwise (see fhld_ros/ros/env.py).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fhld_ros.bagio import bag_topics, read_raw
from fhld_ros.errors import ConfigError
from msg_adapters.family import rclpy_family


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', type=Path, help='rosbag2 bag to publish')
    parser.add_argument('--topics', nargs='+', help='topics to publish (default: all)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    parser.add_argument('--wait-for', metavar='TOPIC', nargs='+', default=[],
                        help='wait (up to --wait-timeout s) until each TOPIC has a matched '
                             'subscriber, so that nothing is published into the void')
    parser.add_argument('--wait-timeout', type=float, default=20.0)
    parser.add_argument('--best-effort', action='store_true',
                        help='publish with best-effort reliability (like most LiDAR drivers)')


def run(args: argparse.Namespace) -> int:
    if not args.rate > 0:
        raise ConfigError(f'--rate must be positive, got {args.rate}')
    available = bag_topics(args.bag, args.topics)  # names any topic the bag lacks
    rclpy.init()
    node = rclpy.create_node('fhld_play')
    try:
        count = _play(node, args, available)
        time.sleep(0.5)  # let reliable writers deliver the tail before the node goes away
        print(f'published {count} messages from {args.bag}')
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _play(node: Node, args: argparse.Namespace, available: dict[str, str]) -> int:
    """Publish the bag's messages on their topics at their log times; returns the count."""
    family = rclpy_family()
    topics = sorted(available)
    reliability = ReliabilityPolicy.BEST_EFFORT if args.best_effort else ReliabilityPolicy.RELIABLE
    qos = QoSProfile(depth=10, reliability=reliability)
    publishers = {t: node.create_publisher(family.cls(available[t]), t, qos) for t in topics}
    clock = None if args.no_clock else node.create_publisher(
        family.cls('rosgraph_msgs/msg/Clock'), '/clock', 10)
    for topic in args.wait_for:
        if topic not in publishers:
            raise ConfigError(f'--wait-for {topic} is not among the published topics')
        _wait_for_subscriber(publishers[topic], topic, args.wait_timeout)
    if args.wait_for:
        # the writer sees the match before the reader does, and a reliable reader drops
        # samples from writers it does not know yet: give discovery a moment to finish
        time.sleep(1.0)
    count, start_wall, start_bag = 0, None, None
    for topic, _, stamp, raw in read_raw(args.bag, topics):
        if start_wall is None:
            start_wall, start_bag = time.monotonic(), stamp
        delay = start_wall + (stamp - start_bag) * 1e-9 / args.rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if clock is not None:
            clock.publish(family.new('rosgraph_msgs/msg/Clock', clock=family.stamp(stamp)))
        publishers[topic].publish(raw)  # rclpy publishes serialized bytes as they are
        count += 1
    return count


def _wait_for_subscriber(publisher: Publisher, topic: str, timeout: float) -> None:
    """Block until the publisher has matched a subscription (not just seen it in the graph)."""
    deadline = time.monotonic() + timeout
    while publisher.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise ConfigError(f'no subscriber appeared on {topic} within {timeout:.0f} s')
        time.sleep(0.05)
