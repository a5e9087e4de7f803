"""What both nodes' shells (lane_detector, camera_lane_detector) build alike: the /lanes,
ego Path and /diagnostics publishers, the wall-clock housekeeping timers, and the sensor input
whose reliability input_reliability sets (SensorInput)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from visualization_msgs.msg import MarkerArray

from fhld_ros.lane_output import LANE_TOPICS

QOS_CHECK_SEC = 1.0


def create_outputs(node: Node, lanes_topic: str) -> tuple[dict[str, Publisher], Publisher]:
    """(suffix -> lane publisher, the /diagnostics publisher), reliable."""
    out_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    types = {'visualization_msgs/msg/MarkerArray': MarkerArray, 'nav_msgs/msg/Path': Path}
    lane_pubs = {suffix: node.create_publisher(types[name], lanes_topic + suffix, out_qos)
                 for suffix, name in LANE_TOPICS.items()}
    return lane_pubs, node.create_publisher(DiagnosticArray, 'diagnostics', out_qos)


def create_housekeeping(node: Node, publish_diagnostics: Callable[[], None],
                        match_publisher_qos: Callable[[], None] | None,
                        inputs: CallbackGroup) -> None:
    """/diagnostics every second and, when given, `match_publisher_qos` (the inputs matched to
    their publishers' QoS, e.g. input_reliability 'auto') in the inputs' group; both on the
    wall clock, so diagnostics keep coming when a bag (ROS time) stops."""
    wall = Clock(clock_type=ClockType.STEADY_TIME)
    node.create_timer(1.0, publish_diagnostics,
                      callback_group=MutuallyExclusiveCallbackGroup(), clock=wall)
    if match_publisher_qos is not None:
        node.create_timer(QOS_CHECK_SEC, match_publisher_qos, callback_group=inputs,
                          clock=wall)


def wanted_reliability(node: Node, topic: str) -> ReliabilityPolicy | None:
    """input_reliability 'auto': reliable unless a best-effort publisher of `topic` exists;
    None while it has no publisher."""
    infos = node.get_publishers_info_by_topic(node.resolve_topic_name(topic))
    if not infos:
        return None
    best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
    return ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE


class SensorInput:
    """A node's sensor subscription: sensor-data QoS (keep last `depth`, volatile) with the
    reliability input_reliability names; with 'auto' reliable (a bag player loses nothing) until
    a best-effort publisher such as a driver appears (match, on the housekeeping timer)."""

    def __init__(self, node: Node, msg_type: type, topic: str, callback: Callable[[Any], None],
                 depth: int, group: CallbackGroup, on_lost: Callable[[Any], None],
                 input_reliability: str) -> None:
        self.node, self.msg_type, self.topic, self.callback = node, msg_type, topic, callback
        self.depth, self.group, self.on_lost = depth, group, on_lost
        self.subscription = None
        self.reliability: ReliabilityPolicy | None = None
        self.subscribe(ReliabilityPolicy.BEST_EFFORT if input_reliability == 'best_effort'
                       else ReliabilityPolicy.RELIABLE)

    def subscribe(self, reliability: ReliabilityPolicy) -> None:
        if self.subscription is not None:
            self.node.destroy_subscription(self.subscription)
        qos = QoSProfile(history=qos_profile_sensor_data.history, depth=self.depth,
                         durability=qos_profile_sensor_data.durability, reliability=reliability)
        self.subscription = self.node.create_subscription(
            self.msg_type, self.topic, self.callback, qos, callback_group=self.group,
            event_callbacks=SubscriptionEventCallbacks(message_lost=self.on_lost))
        self.reliability = reliability
        self.node.get_logger().info(f'subscribed to {self.topic} with {reliability.name} '
                                    'reliability')

    def match(self) -> None:
        """input_reliability 'auto': reliable unless a best-effort publisher appears."""
        wanted = wanted_reliability(self.node, self.topic)
        if wanted is not None and wanted != self.reliability:
            self.subscribe(wanted)
