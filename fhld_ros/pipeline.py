"""The core that the node and `fhld replay` both drive: sweeps and odometry in, lanes out.

    pipeline.receive_odometry(msg)    # any time, any order; a bad message dropped and counted
    pipeline.receive_cloud(msg)       # decode + pose + insert into the rolling grid
    out = pipeline.detect()           # None unless a detection is due (due_window)
    lane_messages(out)                # what is published (lane_output.py)

Lanes come out in the output frame (the odometry's frame, else the cloud's) with stable ids.
A detection is due when a sweep at least 0.9 / rate_hz newer (sweep stamps, not the clock)
than the last detected one is in: the node and a replay of its input detect the same sweeps.

Odometry timing: a sweep's pose is interpolated inside the odometry buffer. A sweep newer than
the newest odometry waits, in stamp order, until odometry reaches its stamp or until the newest
stamp seen (cloud or odometry) is params.odom_wait_sec past it; the wait is measured in the
stream's own time, so a replay is deterministic (the live node adds a clock check for when
messages stop altogether: expire_waiting). A sweep that no odometry covers then (odometry
stopped, or the sweep is older than the buffer) is detected on its own in the cloud frame and
counted as clouds_without_odometry. While odometry stays away, a sweep waits only until a newer
message arrives (the next cloud, or the odometry coming back, which then covers it). A sweep
between two poses too far apart to interpolate waits in the same way: the poses between may
still come (DDS lost them, a reliable writer resends them). The live node also lets late sweeps
in with extrapolated poses (extrapolate_waiting, ros/odometry_wait.py).
"""
from __future__ import annotations

import bisect
import collections
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from fhld_ros.bev import BevSpec
from fhld_ros.intensity import ABSOLUTE
from fhld_ros.lane_output import LaneIdTracker, LaneOutput, ego_lane_bounds
from fhld_ros.parameters import DetectorParams
from fhld_ros.pose_buffer import TIME_BACK_NS, PoseBuffer
from fhld_ros.rolling_grid import BevWindow, RollingBevGrid
from msg_adapters.family import stamp_to_ns
from msg_adapters.odometry import euler_to_matrix, odometry_to_matrix

# sweeps held back by their odometry that still get their own window, at most (the newest of
# them): each costs the newest sweep one more detection of waiting
HELD_BACK_MAX = 2
MAX_PENDING = 32  # waiting sweeps at most, whatever the stamps say (memory bound)
# a sweep this much newer than the last detected one is due: 1 / rate_hz less slack for the
# stamps' jitter (a limit on the clock instead phase-locked detections behind arrivals in the
# node: +40 ms of waiting per sweep)
DUE_FRACTION = 0.9


class LaneDetector(Protocol):
    """Lanes ((K, 3) window frame, ordered) and confidences of one window. A detector may name
    the intensity encoding its windows need (attribute intensity_encoding, default absolute),
    and count the last window's lanes its paint check dropped (lanes_unpainted, default 0)."""

    def __call__(self, window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]: ...


@dataclass
class Intake:
    """What one message did: the sweeps it let into the grid (stamps, oldest first), or why it
    was dropped (a bad message, counted as bad_clouds / bad_odometry; nothing else changed)."""

    stamp_ns: int | None = None
    let_in: list[int] = field(default_factory=list)
    dropped: ValueError | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)


_WAIT = object()  # _pose_for: odometry may still come for this stamp


class LanePipeline:
    """Odometry + clouds -> rolling BEV grid -> detector -> lanes in the output frame."""

    def __init__(self, params: DetectorParams, detector: LaneDetector,
                 expect_odometry: bool = True) -> None:
        self.params = params
        self.detector = detector
        # Sweeps that waited for their odometry and went in together with newer ones (a pose
        # DDS lost, resent later; odometry slower than the sweeps) get windows of their own,
        # oldest first, instead of being overtaken by the newest (take_window)
        self.held_back: collections.deque[int] = collections.deque(maxlen=HELD_BACK_MAX)
        self.min_interval_ns = int(DUE_FRACTION * 1e9 / params.rate_hz)
        self.last_detected_ns: int | None = None
        # False when it is known that no odometry will come (a bag without it): no sweep waits
        self.expect_odometry = expect_odometry
        self.grid = RollingBevGrid(BevSpec(params.size_px, params.resolution_m),
                                   params.accumulate_sec, params.max_sweeps,
                                   getattr(detector, 'intensity_encoding', ABSOLUTE))
        self.odometry = PoseBuffer()
        self.odom_frame: str | None = None
        self.odom_child: str | None = None
        self.lidar_to_base = euler_to_matrix(*params.lidar_to_base)
        self.ids = LaneIdTracker()
        self.output_frame: str | None = None
        self.grid_frame: str | None = None  # the frame of the sweeps in the grid
        self.sweeps_since_detection = 0
        self.wait_ns = round(params.odom_wait_sec * 1e9)
        self.newest_seen_ns: int | None = None  # cloud or odometry: the stream's clock
        self.last_bad_odometry: tuple[int, str] | None = None
        # True from a sweep that odometry did not cover in time until the next odometry
        # message: meanwhile a sweep waits only for any newer message
        self.odometry_stopped = False
        self.pending: collections.deque[tuple] = collections.deque()  # in stamp order
        self.counters = {'clouds': 0, 'odometry': 0, 'detections': 0, 'sweeps_skipped': 0,
                         'resets': 0, 'clouds_without_odometry': 0, 'odometry_timeouts': 0,
                         'clouds_extrapolated': 0, 'bad_clouds': 0, 'bad_odometry': 0,
                         'lanes_unpainted': 0}

    @property
    def uses_odometry(self) -> bool:
        return self.odom_frame is not None

    @property
    def lost_odometry(self) -> bool:
        """Odometry came, then stopped: sweeps go in one at a time, in the cloud frame."""
        return self.odometry_stopped and self.uses_odometry

    @property
    def waiting_stamps(self) -> list[int]:
        """The stamps of the sweeps waiting for their odometry, oldest first."""
        return [waiting[0] for waiting in self.pending]

    def receive_odometry(self, msg: Any) -> Intake:
        """add_odometry, with a bad message dropped and counted (bad_odometry), never raised."""
        try:
            return self.add_odometry(msg)
        except ValueError as exc:
            try:
                bad = (stamp_to_ns(msg.header.stamp), str(exc))
            except (AttributeError, TypeError, ValueError):
                bad = None
            if bad is not None and bad == self.last_bad_odometry:
                return Intake()  # the same message again (the node's second subscription)
            self.last_bad_odometry = bad
            self.counters['bad_odometry'] += 1
            return Intake(dropped=exc.with_traceback(None))

    def receive_cloud(self, msg: Any) -> Intake:
        """add_cloud, with a bad cloud dropped and counted (bad_clouds), never raised."""
        try:
            return self.add_cloud(msg)
        except ValueError as exc:
            self.counters['bad_clouds'] += 1
            # without its traceback: its frames hold the message (a refused 128 MB cloud stayed
            # in memory until a full garbage collection, measured in test_node_memory)
            return Intake(dropped=exc.with_traceback(None))

    def add_odometry(self, msg: Any) -> Intake:
        """Buffer one odometry message and let in the sweeps it covers. Raises ValueError
        (naming the problem), changing nothing, for an empty frame_id (it would be the output
        frame) or a non-finite or non-unit pose."""
        frame = str(msg.header.frame_id)
        if not frame:
            raise ValueError('odometry has an empty frame_id')
        pose = odometry_to_matrix(msg)  # validates before any state changes
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self.odom_frame, self.odom_child = frame, str(msg.child_frame_id)
        self._saw(stamp_ns)
        if not self.odometry.add(stamp_ns, pose):
            return Intake(stamp_ns)  # a pose it has (the node's second odometry subscription)
        self.counters['odometry'] += 1
        # it is back: sweeps wait for their odometry again; but those that waited while it was
        # away, in the gap it left, go in alone now (nothing will fill that gap)
        resumed, self.odometry_stopped = self.odometry_stopped, False
        return Intake(stamp_ns, self._release(wait_in_gaps=not resumed))

    def sensor_pose(self, stamp_ns: int, cloud_frame: str,
                    extrapolate_ns: int = 0) -> np.ndarray | None:
        """Cloud frame -> odometry frame at the stamp; None when no odometry covers it (nor,
        with extrapolate_ns, reaches it by extrapolation: PoseBuffer.extrapolated)."""
        pose = self.odometry.at(stamp_ns)
        if pose is None and extrapolate_ns:
            pose = self.odometry.extrapolated(stamp_ns, extrapolate_ns)
        if pose is None:
            return None
        return pose if cloud_frame == self.odom_child else pose @ self.lidar_to_base

    def add_cloud(self, msg: Any) -> Intake:
        """Decode one sweep; it goes into the grid with the sweeps it let in, or waits for its
        odometry (see the module doc). Raises ValueError (naming the problem) for bad input:
        a malformed cloud, one over params.max_points, an empty frame_id."""
        start = time.perf_counter()
        frame = str(msg.header.frame_id)
        if not frame:  # it would become the output frame without odometry
            raise ValueError('cloud has an empty frame_id')
        xyz, intensity, ring = self.grid.read_cloud(msg, self.params.max_points)
        decoded = time.perf_counter()
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.newest_seen_ns is not None and stamp_ns < self.newest_seen_ns - TIME_BACK_NS:
            # time went back (bag loop): what waits, and the poses, are from the run before
            self.expire_waiting()
            self.odometry.clear()
            self.newest_seen_ns = None
        self._saw(stamp_ns)
        # in stamp order, so the grid (which resets when time goes back) sees them in order
        index = bisect.bisect([s[0] for s in self.pending], stamp_ns)
        self.pending.insert(index, (stamp_ns, frame, (xyz, intensity, ring)))
        let_in = self._release()
        done = time.perf_counter()
        return Intake(stamp_ns, let_in, timings_ms={'decode_ms': (decoded - start) * 1e3,
                                                    'grid_insert_ms': (done - decoded) * 1e3})

    def expire_waiting(self) -> int:
        """Let every waiting sweep in now: with odometry where it covers, else per sweep (the
        live node's clock check when messages stop coming). Returns how many went in."""
        return len(self._release(force=len(self.pending)))

    def extrapolate_waiting(self, until_stamp_ns: int) -> list[int]:
        """Let the waiting sweeps up to until_stamp_ns in (oldest first) with poses
        extrapolated from the newest odometry, as far as params.odom_extrapolate_sec reaches
        past it (the live node's way past odometry that DDS lost). Returns their stamps."""
        reach_ns = round(self.params.odom_extrapolate_sec * 1e9)
        let_in: list[int] = []
        while reach_ns and self.pending and self.pending[0][0] <= until_stamp_ns:
            stamp_ns, frame, cloud = self.pending[0]
            pose = self.sensor_pose(stamp_ns, frame, reach_ns)
            if pose is None:
                break
            self.pending.popleft()
            self._insert(stamp_ns, frame, cloud, pose)
            self.counters['clouds_extrapolated'] += 1
            let_in.append(stamp_ns)
        self._hold_back(let_in)
        return let_in

    def insert_waiting(self) -> bool:
        """Let the oldest waiting sweep in now (at the end of a bag); False when none waits."""
        return bool(self._release(force=1))

    def _saw(self, stamp_ns: int) -> None:
        if self.newest_seen_ns is None or stamp_ns > self.newest_seen_ns:
            self.newest_seen_ns = stamp_ns

    def _pose_for(self, stamp_ns: int, frame: str, wait_in_gaps: bool = True) -> Any:
        """The sweep's pose, None when it will never have one, or _WAIT."""
        newest = self.odometry.newest
        if newest is None:  # none yet, or none since time went back
            return _WAIT if self.expect_odometry or self.uses_odometry else None
        if stamp_ns > newest:
            return _WAIT
        pose = self.sensor_pose(stamp_ns, frame)
        if pose is None and wait_in_gaps and not self.odometry_stopped \
                and stamp_ns >= self.odometry.oldest:
            # in a gap too wide to interpolate: a pose DDS lost may still come (a reliable
            # writer resends it), so it waits as for odometry still on its way
            return _WAIT
        return pose

    def _release(self, force: int = 0, wait_in_gaps: bool = True) -> list[int]:
        """Insert waiting sweeps from the oldest on, while each has its pose, never will, or
        has waited long enough (or is one of the `force` oldest). Returns their stamps."""
        inserted: list[int] = []
        while self.pending:
            stamp_ns, frame, cloud = self.pending[0]
            pose = self._pose_for(stamp_ns, frame, wait_in_gaps)
            if pose is _WAIT:
                # stopped: no full wait, but odometry coming back just after this sweep's
                # cloud still covers it; and a run that never had odometry does not wait
                wait_ns = (0 if self.uses_odometry else -1) if self.odometry_stopped \
                    else self.wait_ns
                overdue = (self.newest_seen_ns - stamp_ns > wait_ns
                           or len(self.pending) > MAX_PENDING)
                if not (len(inserted) < force or overdue):
                    break
                if not self.odometry_stopped and self.uses_odometry:
                    self.counters['odometry_timeouts'] += 1
                self.odometry_stopped = True
                pose = None
            self.pending.popleft()
            self._insert(stamp_ns, frame, cloud, pose)
            inserted.append(stamp_ns)
        self._hold_back(inserted)
        return inserted

    def _hold_back(self, inserted: list[int]) -> None:
        """Sweeps that went into the grid behind a newer one in the same call waited for
        their odometry: note them for a window of their own (held_back)."""
        if self.output_frame == self.odom_frame:
            self.held_back.extend(inserted[:-1])

    def _insert(self, stamp_ns: int, frame: str, cloud: tuple, pose: np.ndarray | None) -> None:
        """The cloud (xyz, intensity, ring or None) into the grid in the odometry frame, or
        alone in the cloud frame when pose is None."""
        xyz, intensity, ring = cloud
        if pose is None and self.uses_odometry:
            self.counters['clouds_without_odometry'] += 1
        output_frame = frame if pose is None else self.odom_frame
        if len(self.grid) and (pose is None or output_frame != self.grid_frame):
            # sweeps without a pose cannot be registered: one at a time; and a grid never
            # mixes frames (odometry stopping or coming back)
            self.grid.reset()
            if output_frame != self.grid_frame:
                self.ids.reset()
        scale = self.params.intensity_scale or None
        if self.grid.insert(stamp_ns, xyz, intensity, np.eye(4) if pose is None else pose,
                            scale, ring=ring):
            self.counters['resets'] += 1
            self.ids.reset()
        self.grid_frame = self.output_frame = output_frame
        self.sweeps_since_detection += 1
        self.counters['clouds'] += 1

    def take_window(self, due_ns: int | None = None) -> BevWindow | None:
        """The current window, or None if no sweep arrived since the last one was taken. A
        sweep held back by its odometry and stamped at or after due_ns comes first, as the
        window around it (the sweeps up to it). Regardless of rate_hz: see due_window."""
        if self.sweeps_since_detection == 0:
            return None
        while self.held_back:
            stamp_ns = self.held_back.popleft()
            if (due_ns is not None and stamp_ns < due_ns) or \
                    stamp_ns >= self.grid.newest_stamp_ns:
                continue  # not due (rate_hz), or the newest itself
            window = self.grid.window(upto_ns=stamp_ns)
            if window is not None and window.stamp_ns == stamp_ns:  # (still in the grid)
                self.sweeps_since_detection -= 1
                return window
        # sweeps that arrived since the last window but were never the newest one detected on
        self.counters['sweeps_skipped'] += self.sweeps_since_detection - 1
        self.sweeps_since_detection = 0
        return self.grid.window()

    def detect_window(self, window: BevWindow) -> LaneOutput:
        """Run the detector on one window; lanes above score_threshold, in the output frame."""
        start = time.perf_counter()
        lanes_window, confidences = self.detector(window)
        detected = time.perf_counter()
        self.counters['lanes_unpainted'] += getattr(self.detector, 'lanes_unpainted', 0)
        keep = [i for i, c in enumerate(confidences) if c >= self.params.score_threshold]
        lanes_window = [np.asarray(lanes_window[i], dtype=np.float64) for i in keep]
        confidences = np.asarray(confidences, dtype=np.float64)[keep]
        lanes = [window.to_output(lane) for lane in lanes_window]
        left, right = ego_lane_bounds(lanes_window)
        self.counters['detections'] += 1
        return LaneOutput(
            stamp_ns=window.stamp_ns, frame_id=self.output_frame or '', lanes=lanes,
            confidences=confidences, ids=self.ids.assign(lanes), outline=window.outline,
            ego_left=None if left is None else lanes[left],
            ego_right=None if right is None else lanes[right],
            timings_ms={'model_ms': (detected - start) * 1e3})

    @property
    def detection_due(self) -> bool:
        """A sweep came since the last window was taken, and the newest is min_interval_ns newer
        than the last detected one (or older: time went back)."""
        newest, last = self.grid.newest_stamp_ns, self.last_detected_ns
        return self.sweeps_since_detection > 0 and newest is not None and (
            last is None or not 0 <= newest - last < self.min_interval_ns)

    def due_window(self) -> BevWindow | None:
        """The window to detect on now, None when no detection is due: the newest sweep (or
        one its odometry held back) once it is min_interval_ns newer than the last detected
        one (or older: time went back).

        Cheap relative to the detector: the node calls it under its lock and runs
        detect_window outside, so incoming sweeps never wait for the model.
        """
        if not self.detection_due:
            return None
        last = self.last_detected_ns
        window = self.take_window(None if last is None else last + self.min_interval_ns)
        if window is not None:
            self.last_detected_ns = window.stamp_ns
        return window

    def detect(self) -> LaneOutput | None:
        """due_window + detect_window; None when no detection is due."""
        start = time.perf_counter()
        window = self.due_window()
        if window is None:
            return None
        raster_ms = (time.perf_counter() - start) * 1e3
        out = self.detect_window(window)
        out.timings_ms['raster_ms'] = raster_ms
        return out
