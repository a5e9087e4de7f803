"""The live node's wall-clock rules for sweeps that wait for their odometry.

InputSilence: "no message at all", confirmed before it acts. Sweeps that wait for their
odometry are bounded in stream time by the pipeline; when messages stop altogether, nothing
newer comes to end the wait, so the node also lets them in after `limit_sec` of wall time
without any message. Silence is read from callbacks that have run, not from what DDS holds:
after the process stalled (a long GIL hold, a page-in, a busy core) every input looks silent
although odometry sits ready in DDS. So the first look that finds the input silent only marks
it; the rule fires at a later look, at least `confirm_sec` on, when no message came in between:
by then the executor has run the callbacks that were ready.

OdometryLateness: how long a sweep waits for odometry that is on its way. A pose can be lost in
DDS (a best-effort reader of a writer whose shared-memory segment a large cloud overran); its
sweep would wait for the next pose that survives. The node learns how long sweeps usually wait
for their odometry (0 when poses come before their clouds, tens of ms behind a LiDAR odometry
that publishes after processing the cloud) and, once a sweep has waited well past that, lets it
in with extrapolated odometry (LanePipeline.extrapolate_waiting). Only waits that ended with a
pose at the usual interval after the one before count: a sweep whose own pose was lost waited
for the next one, which says nothing about how long odometry takes (measured with 23 % of the
poses lost: the patience learned from every wait grew to 170 ms, and 8 of 100 sweeps were
overtaken while they waited).
"""
from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fhld_ros.pipeline import LanePipeline

CONFIRM_SEC = 0.1  # a few executor rounds: callbacks ready after a stall have run by then
WAITS_KEPT = 100  # recent waits of sweeps whose odometry came
MIN_WAITS = 5  # before this many, the patience is START_SEC
START_SEC = 0.1
MIN_PATIENCE_SEC = 0.02  # callbacks that were ready together still run one after the other
PATIENCE_FACTOR = 2.0  # x the 90th percentile of the usual waits
REGULAR_INTERVAL = 1.5  # x the median interval between poses: none was lost in between


class InputSilence:
    """Wall-clock silence of the inputs. heard() on every message; expired() from the polls."""

    def __init__(self, limit_sec: float, confirm_sec: float = CONFIRM_SEC,
                 now: float | None = None) -> None:
        self.limit_sec = limit_sec
        self.confirm_sec = confirm_sec
        self.last_heard = time.monotonic() if now is None else now
        self.silent_since_look: float | None = None  # the look that first found it silent

    def heard(self, now: float | None = None) -> None:
        """A message arrived (any input)."""
        self.last_heard = time.monotonic() if now is None else now

    def expired(self, now: float | None = None) -> bool:
        """True when nothing was heard for limit_sec, as found by two looks confirm_sec apart
        with no message in between."""
        now = time.monotonic() if now is None else now
        if now - self.last_heard <= self.limit_sec:
            self.silent_since_look = None
            return False
        if self.silent_since_look is None or self.silent_since_look < self.last_heard:
            self.silent_since_look = now  # first look at this silence: mark it only
            return False
        return now - self.silent_since_look >= self.confirm_sec


class OdometryLateness:
    """How long a sweep may wait for its odometry before it counts as late (lost on the way)."""

    def __init__(self, limit_sec: float) -> None:
        self.limit_sec = limit_sec  # never longer than odom_wait_sec
        self.waits: collections.deque[float] = collections.deque(maxlen=WAITS_KEPT)
        self.intervals_ns: collections.deque[int] = collections.deque(maxlen=WAITS_KEPT)
        self.newest_pose_ns: int | None = None

    def pose(self, stamp_ns: int) -> bool:
        """A pose arrived; True when it follows the newest one before it at the usual
        interval (so no pose between them was lost), or when no interval is known yet."""
        last, self.newest_pose_ns = self.newest_pose_ns, max(stamp_ns, self.newest_pose_ns or 0)
        if last is None or stamp_ns <= last:
            return last is None
        interval = stamp_ns - last
        self.intervals_ns.append(interval)
        return interval <= REGULAR_INTERVAL * float(np.median(self.intervals_ns))

    def came(self, waited_sec: float) -> None:
        """A sweep's odometry came after it had waited this long (0: it was there first)."""
        self.waits.append(max(waited_sec, 0.0))

    def patience(self) -> float:
        """PATIENCE_FACTOR x the 90th percentile of the recent waits, at least
        MIN_PATIENCE_SEC (START_SEC until MIN_WAITS are known), at most limit_sec."""
        if len(self.waits) < MIN_WAITS:
            usual = START_SEC
        else:
            usual = max(PATIENCE_FACTOR * float(np.percentile(self.waits, 90)), MIN_PATIENCE_SEC)
        return min(usual, self.limit_sec)


class LateSweeps:
    """The sweeps that wait for their odometry, and a thread that lets in, with extrapolated
    poses (LanePipeline.extrapolate_waiting), those that waited longer than OdometryLateness
    allows: a pose DDS lost then costs neither the sweep nor a wait for the next pose.

    `lock` guards the pipeline; cloud_in / odometry_in are called with it held, right after the
    pipeline took the message. `wake` is called when sweeps went in.
    """

    def __init__(self, pipeline: LanePipeline, lock: threading.Lock, limit_sec: float,
                 wake: Callable[[], None]) -> None:
        self.pipeline, self.lock, self.wake = pipeline, lock, wake
        self.lateness = OdometryLateness(limit_sec)
        self.since: dict[int, float] = {}  # waiting sweep stamp -> arrival (monotonic)
        self.tried: set[int] = set()  # waiting sweeps too far past the poses to extrapolate
        # wakes the thread: a new waiting sweep, or close(); taken without `lock` held by the
        # thread, so the callbacks (which hold `lock`) can always notify
        self.changed = threading.Condition()
        self.notified = False
        self.closing = False
        self.thread = threading.Thread(target=self._run, daemon=True, name='late_sweeps')

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        with self.changed:
            self.closing = self.notified = True
            self.changed.notify()
        if self.thread.is_alive():
            self.thread.join(timeout=5)

    def cloud_in(self, stamp_ns: int, arrived: float) -> None:
        """After pipeline.receive_cloud took a sweep (lock held): note the sweep if it waits."""
        if stamp_ns in self.pipeline.waiting_stamps:
            self.since[stamp_ns] = arrived
            with self.changed:
                self.notified = True
                self.changed.notify()
        elif self.pipeline.uses_odometry and not self.pipeline.odometry_stopped:
            self.lateness.came(0.0)  # its odometry was there first

    def odometry_in(self, stamp_ns: int, let_in: list[int], now: float) -> None:
        """After pipeline.receive_odometry took a pose (lock held); it let the sweeps
        `let_in` in."""
        own_pose = self.lateness.pose(stamp_ns)
        for stamp in let_in:
            if stamp in self.since:
                waited = now - self.since.pop(stamp)
                if own_pose:  # not the next pose after one lost on the way
                    self.lateness.came(waited)

    def _run(self) -> None:
        while True:
            timeout = self._let_in_late()
            with self.changed:
                if not self.notified:
                    self.changed.wait(timeout)
                if self.closing:
                    return
                self.notified = False

    def _let_in_late(self) -> float | None:
        """Let the late sweeps in; seconds until the next waiting sweep is late (None: none
        waits)."""
        now = time.monotonic()
        patience = self.lateness.patience()
        with self.lock:
            waiting = set(self.pipeline.waiting_stamps)
            self.since = {s: t for s, t in self.since.items() if s in waiting}
            self.tried &= waiting
            untried = {s: t for s, t in self.since.items() if s not in self.tried}
            late = [s for s, t in untried.items() if t + patience <= now]
            let_in = self.pipeline.extrapolate_waiting(max(late)) if late else []
            self.tried.update(late)  # those it could not reach wait on for their odometry
            for stamp in let_in:
                del self.since[stamp]
            due = [t + patience for s, t in untried.items() if s not in late]
        if let_in:
            self.wake()
        return max(min(due) - now, 0.0) if due else None
