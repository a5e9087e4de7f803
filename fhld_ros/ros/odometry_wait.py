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
import time

import numpy as np

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
