"""`camera_lane_detector` node (ros2 run fhld_ros camera_lane_detector): a thin shell around
CameraPipeline (SALAD, the monocular camera detector).

The image callback only decodes and checks the image against the newest camera_info, keeps it
when it is due (rate_hz on image stamps) and wakes the detection callback (a guard condition,
in its own callback group). Detection never queues up: a wake-up during a running detection is
skipped, and a detection that ends with a newer image waiting starts on it at once, so the
newest image wins and an image replaced before it was detected is counted as overtaken. A bad
message is dropped, counted and warned about (throttled); the node goes on. Topics, frames and
messages: docs/design.md §3, the same /lanes contract as lane_detector.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import (
    CallbackGroup,
    MutuallyExclusiveCallbackGroup,
    ReentrantCallbackGroup,
)
from rclpy.event_handler import QoSMessageLostInfo
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from fhld_ros.lane_output import lane_messages
from fhld_ros.ros.camera_diagnostics import CameraStats
from fhld_ros.ros.declare import declare_params
from fhld_ros.ros.executor import run_node
from fhld_ros.ros.shell import SensorInput, create_housekeeping, create_outputs
from fhld_ros.salad.camera_pipeline import (
    CameraPipeline,
    ImageIntake,
    distortion_notice,
    load_camera_detector,
)
from fhld_ros.salad.parameters import NODE_NAME, CameraParams
from msg_adapters.family import rclpy_family

WARN_THROTTLE_SEC = 5.0
FAMILY = rclpy_family()
# camera_info streamed with the images: best effort matches reliable and best-effort publishers
STREAMED = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
# ... or latched: published once, transient local (its history reaches reliable readers only)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class CameraInfoInput:
    """The camera_info subscription, for a driver that streams it and for one that latches it
    (publishes it once, transient local, often before this node starts). A volatile reader never
    gets a latched message sent before it, and a transient-local reader matches no volatile
    publisher (DDS's durability rule; rclpy's BEST_AVAILABLE chooses transient local when no
    publisher exists yet, and then refuses the usual stream): so it reads STREAMED, and LATCHED
    while every publisher of the topic latches (`match`, on the housekeeping timer)."""

    def __init__(self, node: Node, topic: str, callback: Callable[[CameraInfo], None],
                 group: CallbackGroup) -> None:
        self.node, self.topic, self.callback, self.group = node, topic, callback, group
        self.subscription = None
        self.subscribe(STREAMED)

    def subscribe(self, qos: QoSProfile) -> None:
        if self.subscription is not None:
            self.node.destroy_subscription(self.subscription)
        self.subscription = self.node.create_subscription(
            CameraInfo, self.topic, self.callback, qos, callback_group=self.group)
        self.qos = qos
        if qos is LATCHED:
            self.node.get_logger().info(f'{self.topic} is latched: subscribed transient local')

    def match(self) -> None:
        infos = self.node.get_publishers_info_by_topic(self.node.resolve_topic_name(self.topic))
        if not infos:
            return
        latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                      and i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                      for i in infos)
        wanted = LATCHED if latched else STREAMED
        if wanted is not self.qos:
            self.subscribe(wanted)


class CameraLaneDetectorNode(Node):
    """Images and camera_info in, /lanes, the ego lane Paths and /diagnostics out.

    Keyword arguments go to rclpy's Node (context, parameter_overrides, namespace, ...).
    """

    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.params = declare_params(self, CameraParams)
        self.pipeline = CameraPipeline(self.params, load_camera_detector(self.params))
        self.get_logger().info(f'parameters: {self.params}')
        if self.pipeline.mount_warning:
            self.get_logger().warning(self.pipeline.mount_warning)
        self.lock = threading.Lock()  # the pipeline: input callbacks vs taking an image
        self.detecting = threading.Lock()
        self.said_distorted = False
        self.stats = CameraStats()
        self._create_interfaces()
        self.get_logger().info(f'camera_lane_detector ready: SALAD on '
                               f'{self.resolve_topic_name(self.image_input()[1])}')

    def _create_interfaces(self) -> None:
        p = self.params
        # images and camera_info one at a time, in arrival order
        self.inputs = MutuallyExclusiveCallbackGroup()
        # keep last 2: only the newest image counts
        self.images = SensorInput(self, *self.image_input(), self.on_image, 2, self.inputs,
                                  self.on_lost, p.input_reliability)
        # streamed or latched, only the newest counts
        self.camera_info = CameraInfoInput(self, p.camera_info_topic, self.on_camera_info,
                                           self.inputs)
        self.lane_pubs, self.diag_pub = create_outputs(self, p.lanes_topic)
        # Reentrant: a wake-up that finds a detection running returns at once (never queues)
        self.wake_detection = self.create_guard_condition(
            self.on_detection_due, callback_group=ReentrantCallbackGroup())
        create_housekeeping(self, self.publish_diagnostics, self.match_publishers, self.inputs)

    def match_publishers(self) -> None:
        """The inputs' QoS to their publishers': camera_info's durability, and the images'
        reliability with input_reliability 'auto'."""
        if self.params.input_reliability == 'auto':
            self.images.match()
        self.camera_info.match()

    def image_input(self) -> tuple[type, str]:
        """The image message type and topic image_transport names (image_transport's topic
        convention: a transport's messages on <base topic>/<transport>)."""
        if self.params.image_transport == 'compressed':
            return CompressedImage, self.params.image_topic.rstrip('/') + '/compressed'
        return Image, self.params.image_topic

    def _drop(self, what: str, exc: Exception) -> None:
        """A message dropped (bad input) or one that failed unexpectedly: counted, warned
        about (throttled); the node goes on."""
        self.stats.error(what, exc)
        self.get_logger().warning(f'dropped {what.replace("_", " ")}: {exc}',
                                  throttle_duration_sec=WARN_THROTTLE_SEC)

    def on_lost(self, info: QoSMessageLostInfo) -> None:
        """DDS says images never reached this subscription."""
        self.stats.counts['images_lost_in_dds'] += info.total_count_change
        self.stats.event('images_lost', value=info.total_count_change)
        self.get_logger().warning(
            f'DDS lost {info.total_count} images on {self.images.topic} before they '
            'reached the node', throttle_duration_sec=WARN_THROTTLE_SEC)

    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            with self.lock:
                problem = self.pipeline.receive_camera_info(msg)
                camera = self.pipeline.camera
        except Exception as exc:  # an unexpected failure never takes the node down either
            problem, camera = exc, None
        if problem is not None:
            self._drop('bad_camera_info', problem)
        elif camera is not None and camera.lens is not None and not self.said_distorted:
            self.said_distorted = True
            text, log = distortion_notice(self.params.image_topic, self.params.camera_info_topic,
                                          camera.lens)
            getattr(self.get_logger(), log)(text)

    def on_image(self, msg: Image) -> None:
        arrived = time.monotonic()
        self.stats.image_received(arrived)
        try:
            with self.lock:
                intake = self.pipeline.receive_image(msg)
        except Exception as exc:
            intake = ImageIntake(dropped=exc)
        if intake.dropped is not None:
            self._drop('bad_images', intake.dropped)
            return
        if intake.replaced:
            self.stats.event('images_overtaken', arrived)
        if intake.due:
            self.stats.image_due(intake.stamp_ns, arrived, intake.timings_ms['image_decode_ms'])
            self.wake_detection.trigger()

    def on_detection_due(self) -> None:
        while self.detecting.acquire(blocking=False):  # else one is running: never queue
            try:
                while self.detect_once():
                    pass
            finally:
                self.detecting.release()
            # an image that came in after the last check found the lock still held
            if not self.pipeline.detection_due:
                return

    def detect_once(self) -> bool:
        """Detect on the waiting image, if any; True when a detection ran."""
        try:
            with self.lock:
                image = self.pipeline.due_image()
            if image is None:
                return False
            start = time.monotonic()
            out = self.pipeline.detect_image(image)
            detected = time.monotonic()
            for suffix, cdr in lane_messages(out).items():
                self.lane_pubs[suffix].publish(cdr)
            done = time.monotonic()
            self.stats.detection_done(out.stamp_ns, start, out.timings_ms, done,
                                      (done - detected) * 1e3, out.lanes_plane_height_m,
                                      out.lanes_pitch_deg)
            return True
        except Exception as exc:
            self.stats.error('detection_errors', exc)
            self.get_logger().error(f'detection failed: {exc}',
                                    throttle_duration_sec=WARN_THROTTLE_SEC)
            return False

    def publish_diagnostics(self) -> None:
        with self.lock:
            counters = dict(self.pipeline.counters)
        status = self.stats.status(counters, getattr(self.images.reliability, 'name', ''),
                                   self.get_fully_qualified_name())
        self.diag_pub.publish(DiagnosticArray(
            header=FAMILY.header(self.get_clock().now().nanoseconds, ''), status=[status]))


def main(args: list[str] | None = None) -> int:
    """Run the node until a signal; 0 when stopped, 2 (one line) for bad parameters or weights
    (ros/executor.py: run_node, as lane_detector's)."""
    return run_node(NODE_NAME, CameraLaneDetectorNode, args)
