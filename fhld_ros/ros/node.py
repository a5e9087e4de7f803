"""`lane_detector` node (ros2 run fhld_ros lane_detector): a thin shell around LanePipeline.

The cloud callback only decodes and inserts into the rolling grid, then wakes the detection
callback (a guard condition; so does odometry that lets a waiting sweep in); a timer (ROS time,
so use_sim_time works) polls as well. Both run in their own callback group and never queue up:
a wake-up with no new sweep, or during a running detection, is skipped, and a detection that
ends with a newer sweep waiting starts on it at once. A bad message is dropped, counted and
warned about (throttled). A sweep waits for its odometry in stream time (LanePipeline); the
poll and the diagnostics timer add a wall-clock check for when messages stop altogether, a
thread lets in with extrapolated poses the sweeps whose pose DDS lost (ros/odometry_wait.py),
and the node warns (throttled) while sweeps go in per sweep for want of odometry. Topics, frames
and messages: docs/design.md §3.
"""
from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import QoSMessageLostInfo, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from fhld_ros.detectors import make_detector
from fhld_ros.lane_output import lane_messages
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import Intake, LanePipeline
from fhld_ros.ros.declare import declare_params
from fhld_ros.ros.diagnostics import NodeStats
from fhld_ros.ros.executor import run_node
from fhld_ros.ros.odometry_wait import InputSilence, LateSweeps
from fhld_ros.ros.shell import SensorInput, create_housekeeping, create_outputs
from msg_adapters.family import rclpy_family

WARN_THROTTLE_SEC = 5.0
# Detection runs when one is due (LanePipeline.due_window). The cloud callback wakes it; the
# timer polls this often (ROS time) as a fallback.
POLL_HZ = 20.0
FAMILY = rclpy_family()


class LaneDetectorNode(Node):
    """Clouds and odometry in, /lanes, the ego lane Paths and /diagnostics out.

    Keyword arguments go to rclpy's Node (context, parameter_overrides, namespace, ...).
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('lane_detector', **kwargs)
        self.params = declare_params(self, DetectorParams)
        self.pipeline = LanePipeline(self.params, make_detector(self.params))
        # logged once they proved usable: a bad value gives one line on stderr, nothing else
        self.get_logger().info(f'parameters: {self.params}')
        self.lock = threading.Lock()  # the pipeline: cloud / odometry callbacks vs detection
        self.detecting = threading.Lock()
        self.said_no_odometry = False
        self.said_odometry_stopped = False
        # Sweeps waiting for odometry also go in when no message at all came for
        # odom_wait_sec of wall time (the pipeline's own bound needs newer messages). Not ROS
        # time: with use_sim_time it stops with the bag, the poll with it.
        self.silence = InputSilence(self.params.odom_wait_sec)
        self.stats = NodeStats(self.pipeline.min_interval_ns)
        self._create_interfaces()
        # sweeps whose pose DDS lost go in extrapolated once late (odometry_wait.py)
        self.late_sweeps = LateSweeps(self.pipeline, self.lock, self.params.odom_wait_sec,
                                      self.wake_detection.trigger)
        if self.params.odom_extrapolate_sec > 0:
            self.late_sweeps.start()
        self.get_logger().info(f'lane_detector ready: {self.params.detector} detector, clouds '
                               f'on {self.resolve_topic_name(self.params.points_topic)}')

    def _create_interfaces(self) -> None:
        p = self.params
        # Clouds one at a time, in arrival order (an older stamp resets the grid); odometry in
        # a group of its own, so a pose arriving during a cloud's ingest runs on another worker
        # (it waits for the pipeline lock) instead of keeping the executor awake until then.
        self.inputs = MutuallyExclusiveCallbackGroup()
        odometry = MutuallyExclusiveCallbackGroup()
        # Reentrant on purpose: a poll that finds a detection running returns at once. In a
        # mutually exclusive group the timer would stay ready while its callback runs and
        # rclpy's executor would spin on it (measured: ~45 % of a core, detections 2x slower).
        detection = ReentrantCallbackGroup()
        # keep last 5: clouds one at a time, a reliable reader loses nothing from a bag player
        self.points = SensorInput(self, PointCloud2, p.points_topic, self.on_cloud, 5,
                                  self.inputs, lambda info: self.on_lost('clouds', info),
                                  p.input_reliability)
        # Odometry twice: best effort, so that a pose lost in DDS never holds back the next (a
        # reliable reader delivers in order: with Fast DDS's default 512 kB shared-memory
        # segment, which a 3 MB cloud published after the pose overruns, poses came 0.9-2.9 s
        # late, p50 950 ms, against 2-4 ms best effort); and reliable, when the publisher is,
        # for the poses the best-effort reader lost, resent by the writer up to seconds later
        # (with 80 % of the poses lost, sweeps with neither pose nor reach for extrapolation
        # went in alone and reset the grid). The pipeline keeps one pose per stamp.
        self.create_subscription(
            Odometry, p.odom_topic, self.on_odometry,
            QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT),
            callback_group=odometry,
            event_callbacks=SubscriptionEventCallbacks(
                message_lost=lambda info: self.on_lost('odometry', info)))
        self.create_subscription(
            Odometry, p.odom_topic, self.on_odometry,
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE),
            callback_group=odometry,  # (a best-effort publisher simply does not match it)
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=lambda info: None))
        self.lane_pubs, self.diag_pub = create_outputs(self, p.lanes_topic)
        # Detection polls on ROS time (sim time for bags); housekeeping follows the wall, so
        # diagnostics keep coming when a bag stops.
        self.create_timer(1.0 / max(p.rate_hz, POLL_HZ), self.on_detection_due,
                          callback_group=detection)
        # The cloud callback wakes detection at once; with the poll alone a sweep waited up to
        # a poll period for its detection to start.
        self.wake_detection = self.create_guard_condition(self.on_detection_due,
                                                          callback_group=detection)
        create_housekeeping(self, self.publish_diagnostics,
                            self.points.match if p.input_reliability == 'auto' else None,
                            self.inputs)

    @property
    def points_reliability(self) -> ReliabilityPolicy | None:
        return self.points.reliability

    def _drop(self, what: str, exc: Exception) -> None:
        """A message the pipeline dropped (bad input), or one that failed unexpectedly: counted,
        warned about (throttled); the node goes on."""
        self.stats.error(what, exc)
        self.get_logger().warning(f'dropped {what.replace("_", " ")}: {exc}',
                                  throttle_duration_sec=WARN_THROTTLE_SEC)

    def on_lost(self, what: str, info: QoSMessageLostInfo) -> None:
        """DDS says messages never reached this subscription (a best-effort writer's samples
        lost on the way, or a reliable writer's dropped from its history before delivery)."""
        self.stats.lost_in_transport(what, info.total_count_change)
        if what == 'clouds':
            self.get_logger().warning(
                f'DDS lost {info.total_count} clouds on {self.params.points_topic} before they '
                'reached the node (large clouds over a best-effort transport: raise the '
                'shared-memory segment size, see the README on DDS)',
                throttle_duration_sec=WARN_THROTTLE_SEC)

    def _report_odometry(self) -> None:
        """Warn (throttled) while sweeps go in without odometry; say when it is back."""
        if self.pipeline.lost_odometry:
            self.said_odometry_stopped = True
            self.get_logger().warning(
                f'no odometry on {self.params.odom_topic} within odom_wait_sec '
                f'{self.params.odom_wait_sec:g} s of the sweeps: detecting per sweep in the '
                'cloud frame', throttle_duration_sec=WARN_THROTTLE_SEC)
        elif self.said_odometry_stopped and self.pipeline.uses_odometry:
            self.said_odometry_stopped = False
            self.get_logger().info(f'odometry on {self.params.odom_topic} is back: detecting '
                                   f'in {self.pipeline.odom_frame} again')

    def on_odometry(self, msg: Odometry) -> None:
        self.silence.heard()
        try:
            with self.lock:
                intake = self.pipeline.receive_odometry(msg)
                if intake.stamp_ns is not None:
                    self.late_sweeps.odometry_in(intake.stamp_ns, intake.let_in,
                                                 time.monotonic())
        except Exception as exc:  # an unexpected failure never takes the node down either
            intake = Intake(dropped=exc)
        if intake.dropped is not None:
            self._drop('bad_odometry', intake.dropped)
            return
        if self.said_odometry_stopped:
            self._report_odometry()
        if intake.let_in:
            # A sweep that came before the odometry of its stamp went in just now; without this
            # wake-up it waited for the next poll (measured: +31 ms on 1 sweep in 6).
            self.wake_detection.trigger()

    def on_cloud(self, msg: PointCloud2) -> None:
        arrived = time.monotonic()
        self.silence.heard(arrived)
        self.stats.cloud_received(arrived)
        try:
            with self.lock:
                intake = self.pipeline.receive_cloud(msg)
                if intake.dropped is None:
                    self.stats.cloud_ingested(intake.stamp_ns, arrived, time.monotonic())
                    no_odometry = not self.pipeline.uses_odometry
                    self.late_sweeps.cloud_in(intake.stamp_ns, arrived)
        except Exception as exc:
            intake = Intake(dropped=exc)
        if intake.dropped is not None:
            self._drop('bad_clouds', intake.dropped)
            return
        self.wake_detection.trigger()
        self._report_odometry()
        if no_odometry and not self.said_no_odometry:
            self.said_no_odometry = True
            self.get_logger().info(f'no odometry on {self.params.odom_topic} yet: '
                                   'detecting per sweep in the cloud frame')

    def destroy_node(self) -> None:
        self.late_sweeps.close()
        super().destroy_node()

    def on_detection_due(self) -> None:
        if not self.detecting.acquire(blocking=False):
            return  # the previous detection is still running: never queue
        try:
            self.expire_waiting()
            # A sweep that came in during a detection was skipped by its wake-up: go on.
            while self.detect_once():
                pass
        finally:
            self.detecting.release()

    def expire_waiting(self) -> bool:
        """Sweeps still waiting for odometry after odom_wait_sec without any message go in
        now (per sweep where nothing covers them); True when any did."""
        if not self.pipeline.waiting_stamps or not self.silence.expired():
            return False
        with self.lock:
            inserted = self.pipeline.expire_waiting()
        self._report_odometry()
        return inserted > 0

    def detect_once(self) -> bool:
        """Detect on the newest sweep if it is due; True when a detection ran."""
        try:
            start = time.monotonic()
            with self.lock:
                window = self.pipeline.due_window()
                timed_out = self.pipeline.odometry_stopped  # (the first waited odom_wait_sec)
            if window is None:
                return False
            rastered = time.monotonic()
            out = self.pipeline.detect_window(window)
            detected = time.monotonic()
            for suffix, cdr in lane_messages(out).items():
                self.lane_pubs[suffix].publish(cdr)
            self.stats.detection_done(out.stamp_ns, start, rastered, detected, time.monotonic(),
                                      odometry_timed_out=timed_out)
            return True
        except Exception as exc:
            self.stats.error('detection_errors', exc)
            self.get_logger().error(f'detection failed: {exc}',
                                    throttle_duration_sec=WARN_THROTTLE_SEC)
            return False

    def publish_diagnostics(self) -> None:
        if self.expire_waiting():  # the poll runs on ROS time, which may have stopped
            self.wake_detection.trigger()
        status = self.stats.status(self.pipeline.counters,
                                   getattr(self.points.reliability, 'name', ''),
                                   self.get_fully_qualified_name(),
                                   odometry_stopped=self.said_odometry_stopped)
        self.diag_pub.publish(DiagnosticArray(
            header=FAMILY.header(self.get_clock().now().nanoseconds, ''), status=[status]))


def main(args: list[str] | None = None) -> int:
    """Run the node until a signal; 0 when stopped, 2 (one line) for bad parameters or weights
    (ros/executor.py: run_node)."""
    return run_node('lane_detector', LaneDetectorNode, args)
