"""fhld_ros.ros.odometry_wait: the live node's wall-clock rules, on a replayed timeline."""
from __future__ import annotations

from fhld_ros.ros.odometry_wait import (
    MIN_PATIENCE_SEC,
    START_SEC,
    InputSilence,
    OdometryLateness,
)


def test_silence_needs_two_looks_with_no_message_between():
    silence = InputSilence(1.0, confirm_sec=0.1, now=0.0)
    assert not silence.expired(now=0.9)
    # the process stalled 1.5 s: the first look only marks the silence ...
    assert not silence.expired(now=1.5)
    silence.heard(now=1.52)  # ... the odometry that was ready in DDS runs right after
    assert not silence.expired(now=1.6)
    assert not silence.expired(now=2.6)  # silent again: a fresh first look
    assert not silence.expired(now=2.65)  # too soon after it
    assert silence.expired(now=2.71)
    silence.heard(now=3.0)
    assert not silence.expired(now=3.5)


def test_patience_follows_the_usual_wait_and_ignores_waits_behind_lost_poses():
    lateness = OdometryLateness(limit_sec=1.0)
    assert lateness.patience() == START_SEC  # nothing learned yet
    stamp = 0
    for _ in range(20):  # poses every 100 ms come 40 ms after their sweeps
        stamp += 100_000_000
        assert lateness.pose(stamp)
        lateness.came(0.04)
    assert abs(lateness.patience() - 0.08) < 1e-9
    # a pose lost: the next one is 200 ms on, and its sweeps' waits do not count
    assert not lateness.pose(stamp + 200_000_000)
    assert lateness.pose(stamp + 300_000_000)
    # poses that come before their sweeps: as short as callbacks allow, never 0
    for _ in range(100):
        lateness.came(0.0)
    assert lateness.patience() == MIN_PATIENCE_SEC
    # and never longer than odom_wait_sec
    slow = OdometryLateness(limit_sec=0.05)
    for _ in range(10):
        slow.came(0.3)
    assert slow.patience() == 0.05
