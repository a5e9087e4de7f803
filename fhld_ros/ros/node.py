"""`lane_detector` node (ros2 run fhld_ros lane_detector): a thin shell around LanePipeline.

The cloud callback only decodes and inserts into the rolling grid, then wakes the detection
callback (a guard condition; so does odometry that lets a waiting sweep in); a timer (ROS time,
so use_sim_time works) polls as well. Both run in their own callback group and never queue up:
a wake-up with no new sweep, or during a running detection, is skipped, and a detection that
ends with a newer sweep waiting starts on it at once. A bad message is dropped, counted and
warned about (throttled).
"""
from __future__ import annotations

import collections
import dataclasses
import gc
import sys
import threading
import time

import numpy as np

from fhld_ros.ros.parameters import DESCRIPTIONS, DetectorParams

WARN_THROTTLE_SEC = 5.0
QOS_CHECK_SEC = 1.0
# Detection runs when a sweep at least 1 / rate_hz newer than the last detected one is in. The
# cloud callback wakes it; the timer polls this often (ROS time) as a fallback.
POLL_HZ = 20.0
GIL_SWITCH_SEC = 0.0005  # see main()
# Stage breakdown in /diagnostics (medians, ms): ingest = cloud callback (decode + insert),
# wait = sweep arrival -> its detection starts, raster = window raster, detect = model and
# tracking, publish = /lanes + ego paths. latency_ms = arrival -> published.
STAGES = ('ingest', 'wait', 'raster', 'detect', 'publish')


def main(args: list[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from fhld_ros.ros.executor import HandoffExecutor

    rclpy.init(args=args)
    try:
        node = make_node()
    except ValueError as exc:  # bad parameters or checkpoint: one clear line, no traceback
        print(f'lane_detector: error: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    # The executor's Python wait loop and the detection thread share the GIL; the model gives it
    # up in every torch op and, at the default 5 ms switch interval, waited that long to get it
    # back each time (measured: detections 2x slower in the node than alone).
    sys.setswitchinterval(GIL_SWITCH_SEC)
    # A full garbage collection walks every object torch and rclpy created at start-up (~200k,
    # ~95 ms here) holding the GIL, and stalled callbacks at random (measured: cloud callbacks
    # up to 60-100 ms late). Frozen objects are left out of collections.
    gc.freeze()
    # A MultiThreadedExecutor that cannot starve its workers (see fhld_ros/ros/executor.py)
    executor = HandoffExecutor(num_threads=3)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        # Jazzy's Executor.shutdown() does not wait for callbacks still running in the pool;
        # destroying the node under one crashed the process (SIGSEGV, ~1 in 8 stops on a busy
        # machine). Join the pool first.
        pool = getattr(executor, '_executor', None)
        if pool is not None:
            pool.shutdown(wait=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def make_node():
    """Build the node class lazily so importing this module needs no rclpy."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from nav_msgs.msg import Odometry, Path
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
    from rclpy.clock import Clock, ClockType
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from fhld_ros.detectors import make_detector
    from fhld_ros.pipeline import LanePipeline
    from msg_adapters.family import rclpy_family, stamp_to_ns
    from msg_adapters.lanes import lane_to_path, lanes_to_marker_array

    family = rclpy_family()

    class LaneDetectorNode(Node):
        def __init__(self) -> None:
            super().__init__('lane_detector')
            self.params = self._declare_parameters()
            self.get_logger().info(f'parameters: {self.params}')
            self.pipeline = LanePipeline(self.params, make_detector(self.params))
            self.lock = threading.Lock()
            self.received_at: dict[int, float] = {}
            self.latencies_ms: collections.deque[float] = collections.deque(maxlen=300)
            # per-stage times (ms) of recent sweeps / detections, medians in /diagnostics
            self.stages_ms = {name: collections.deque(maxlen=300) for name in STAGES}
            self.counts = collections.Counter()
            self.last_error = ''
            self.said_no_odometry = False
            self.started = time.monotonic()

            inputs = MutuallyExclusiveCallbackGroup()
            # Reentrant on purpose: a poll that finds a detection running returns at once. In a
            # mutually exclusive group the timer would stay ready while its callback runs and
            # rclpy's executor would spin on it (measured: ~45 % of a core, detections 2x slower).
            detection = ReentrantCallbackGroup()
            self.detecting = threading.Lock()
            self.inputs = inputs
            p = self.params
            self.points_sub = None
            self.points_reliability: ReliabilityPolicy | None = None
            self._subscribe_points(ReliabilityPolicy.BEST_EFFORT
                                   if p.input_reliability == 'best_effort'
                                   else ReliabilityPolicy.RELIABLE)
            self.create_subscription(Odometry, p.odom_topic, self.on_odometry, 50,
                                     callback_group=inputs)
            out_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
            self.lanes_pub = self.create_publisher(MarkerArray, p.lanes_topic, out_qos)
            self.left_pub = self.create_publisher(Path, f'{p.lanes_topic}/ego_left', out_qos)
            self.right_pub = self.create_publisher(Path, f'{p.lanes_topic}/ego_right', out_qos)
            self.diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', out_qos)
            # Detection polls on ROS time (sim time for bags); housekeeping follows the wall, so
            # diagnostics keep coming when a bag stops. rate_hz limits detections by sweep
            # stamps, not by when the last detection ran: a limit on the clock phase-locked
            # detections behind arrivals (measured: +40 ms of waiting per sweep).
            self.min_interval_ns = int(0.9e9 / p.rate_hz)  # slack for stamp jitter
            self.last_detected_stamp_ns: int | None = None
            self.create_timer(1.0 / max(p.rate_hz, POLL_HZ), self.on_detection_due,
                              callback_group=detection)
            # The cloud callback wakes detection at once; with the poll alone a sweep waited up
            # to a poll period for its detection to start.
            self.wake_detection = self.create_guard_condition(self.on_detection_due,
                                                              callback_group=detection)
            wall = Clock(clock_type=ClockType.STEADY_TIME)
            self.create_timer(1.0, self.publish_diagnostics,
                              callback_group=MutuallyExclusiveCallbackGroup(), clock=wall)
            if p.input_reliability == 'auto':
                self.create_timer(QOS_CHECK_SEC, self.match_publisher_qos, callback_group=inputs,
                                  clock=wall)
            self.get_logger().info(f'lane_detector ready: {p.detector} detector, clouds on '
                                   f'{self.resolve_topic_name(p.points_topic)}')

        def _declare_parameters(self) -> DetectorParams:
            defaults, values = DetectorParams(), {}
            for item in dataclasses.fields(DetectorParams):
                default = getattr(defaults, item.name)
                default = list(default) if isinstance(default, tuple) else default
                descriptor = ParameterDescriptor(description=DESCRIPTIONS[item.name])
                value = self.declare_parameter(item.name, default, descriptor).value
                values[item.name] = tuple(value) if isinstance(value, list) else value
            return DetectorParams(**values)

        def _subscribe_points(self, reliability: ReliabilityPolicy) -> None:
            if self.points_sub is not None:
                self.destroy_subscription(self.points_sub)
            # Sensor-data QoS (keep last 5, volatile) with the chosen reliability: a reliable
            # subscription loses nothing from a bag player, a best-effort one takes drivers.
            qos = QoSProfile(history=qos_profile_sensor_data.history, depth=5,
                             durability=qos_profile_sensor_data.durability,
                             reliability=reliability)
            self.points_sub = self.create_subscription(
                PointCloud2, self.params.points_topic, self.on_cloud, qos,
                callback_group=self.inputs)
            self.points_reliability = reliability
            self.get_logger().info(f'subscribed to {self.params.points_topic} with '
                                   f'{reliability.name} reliability')

        def match_publisher_qos(self) -> None:
            """input_reliability 'auto': reliable unless a best-effort publisher appears."""
            infos = self.get_publishers_info_by_topic(
                self.resolve_topic_name(self.params.points_topic))
            if not infos:
                return
            best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                              for i in infos)
            wanted = ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE
            if wanted != self.points_reliability:
                self._subscribe_points(wanted)

        def _drop(self, what: str, exc: Exception) -> None:
            self.counts[what] += 1
            self.last_error = f'{what}: {exc}'
            self.get_logger().warning(f'dropped {what.replace("_", " ")}: {exc}',
                                      throttle_duration_sec=WARN_THROTTLE_SEC)

        def on_odometry(self, msg: Odometry) -> None:
            try:
                with self.lock:
                    newest = self.pipeline.grid.newest_stamp_ns
                    self.pipeline.add_odometry(msg)
                    inserted = self.pipeline.grid.newest_stamp_ns != newest
            except Exception as exc:  # a bad message never takes the node down
                self._drop('bad_odometry', exc)
                return
            if inserted:
                # A sweep that came before the odometry of its stamp went in just now; without
                # this wake-up it waited for the next poll (measured: +31 ms on 1 sweep in 6).
                self.wake_detection.trigger()

        def on_cloud(self, msg: PointCloud2) -> None:
            arrived = time.monotonic()
            self.counts['clouds_received'] += 1
            try:
                with self.lock:
                    self.pipeline.add_cloud(msg)
                    self.stages_ms['ingest'].append((time.monotonic() - arrived) * 1e3)
                    self.received_at[stamp_to_ns(msg.header.stamp)] = arrived
                    if len(self.received_at) > 100:
                        self.received_at.pop(next(iter(self.received_at)))
                    no_odometry = not self.pipeline.uses_odometry
            except Exception as exc:
                self._drop('bad_clouds', exc)
                return
            self.wake_detection.trigger()
            if no_odometry and not self.said_no_odometry:
                self.said_no_odometry = True
                self.get_logger().info(f'no odometry on {self.params.odom_topic} yet: '
                                       'detecting per sweep in the cloud frame')

        def on_detection_due(self) -> None:
            if not self.detecting.acquire(blocking=False):
                return  # the previous detection is still running: never queue
            try:
                # A sweep that came in during a detection was skipped by its wake-up: go on.
                while self.detect_once():
                    pass
            finally:
                self.detecting.release()

        def detect_once(self) -> bool:
            """Detect on the newest sweep if it is due; True when a detection ran."""
            try:
                start = time.monotonic()
                with self.lock:
                    newest, last = self.pipeline.grid.newest_stamp_ns, self.last_detected_stamp_ns
                    if newest is None or (last is not None and
                                          0 <= newest - last < self.min_interval_ns):
                        return False  # nothing new, or too soon after the last detected sweep
                    window = self.pipeline.take_window()
                if window is None:
                    return False
                self.last_detected_stamp_ns = window.stamp_ns
                rastered = time.monotonic()
                out = self.pipeline.detect_window(window)
                detected = time.monotonic()
                header = family.header(out.stamp_ns, out.frame_id)
                self.lanes_pub.publish(lanes_to_marker_array(
                    family, header, out.lanes, out.confidences, out.ids, out.outline))
                self.left_pub.publish(lane_to_path(family, header, out.ego_left))
                self.right_pub.publish(lane_to_path(family, header, out.ego_right))
                done = time.monotonic()
                arrived = self.received_at.get(out.stamp_ns)
                if arrived is not None:
                    self.latencies_ms.append((done - arrived) * 1e3)
                    self.stages_ms['wait'].append((start - arrived) * 1e3)
                for name, (a, b) in {'raster': (start, rastered), 'detect': (rastered, detected),
                                     'publish': (detected, done)}.items():
                    self.stages_ms[name].append((b - a) * 1e3)
                return True
            except Exception as exc:
                self.counts['detection_errors'] += 1
                self.last_error = f'detection: {exc}'
                self.get_logger().error(f'detection failed: {exc}',
                                        throttle_duration_sec=WARN_THROTTLE_SEC)
                return False

        def publish_diagnostics(self) -> None:
            counters = dict(self.pipeline.counters, **self.counts)
            elapsed = max(time.monotonic() - self.started, 1e-9)
            values = {k: str(v) for k, v in sorted(counters.items())}
            values['cloud_rate_hz'] = f'{counters.get("clouds", 0) / elapsed:.2f}'
            values['detection_rate_hz'] = f'{counters.get("detections", 0) / elapsed:.2f}'
            if self.latencies_ms:
                p50, p95 = np.percentile(np.asarray(self.latencies_ms), [50, 95])
                values['latency_ms_p50'], values['latency_ms_p95'] = f'{p50:.1f}', f'{p95:.1f}'
            for name, times in self.stages_ms.items():
                if times:
                    values[f'stage_{name}_ms_p50'] = f'{np.median(np.asarray(times)):.1f}'
            values['input_reliability'] = getattr(self.points_reliability, 'name', '')
            values['last_error'] = self.last_error
            dropped = counters.get('bad_clouds', 0) + counters.get('bad_odometry', 0)
            status = DiagnosticStatus(
                level=DiagnosticStatus.WARN if dropped or self.last_error else DiagnosticStatus.OK,
                name='fhld_ros: lane_detector', hardware_id=self.get_fully_qualified_name(),
                message=f'{dropped} bad messages dropped' if dropped else 'running',
                values=[KeyValue(key=k, value=v) for k, v in values.items()])
            msg = DiagnosticArray(header=family.header(self.get_clock().now().nanoseconds, ''),
                                  status=[status])
            self.diag_pub.publish(msg)

    return LaneDetectorNode()


if __name__ == '__main__':
    sys.exit(main())
