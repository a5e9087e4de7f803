"""/diagnostics levels from the last few seconds: assess() on windows, and NodeStats on
timelines with injected times (no sleeping). The node's wiring: test/test_node.py."""
from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from fhld_ros.ros.diagnostics import THRESHOLDS, NodeStats, WindowSummary, assess

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
SWEEP_NS = 100_000_000
MIN_INTERVAL_NS = 90_000_000  # the node's at rate_hz 10


def clean(**changes) -> WindowSummary:
    """5 s of 10 Hz clouds, all detected 60 ms after arrival, the newest 0.1 s ago."""
    return WindowSummary(**{**dict(seconds=5.0, clouds=50, detections=50, latency_p95_ms=60.0,
                                   since_cloud=0.1), **changes})


def test_a_clean_window_is_ok():
    assert assess(clean()) == (OK, 'running')


def test_before_the_first_cloud_the_node_warns_that_it_waits():
    assert assess(WindowSummary(seconds=1.0)) == (WARN, 'no clouds received yet')


def test_stale_input_warns_then_errors():
    assert assess(clean(since_cloud=THRESHOLDS.stale_warn_sec))[0] == OK
    assert assess(clean(since_cloud=3.0)) == (WARN, 'input stale: no clouds for 3.0 s (> 2 s)')
    assert assess(clean(since_cloud=12.0)) == (
        ERROR, 'input stale: no clouds for 12.0 s (> 10 s)')


def test_any_drop_warns_and_over_half_is_an_error():
    assert assess(clean(bad_clouds=1)) == (
        WARN, 'dropped 1 of 50 clouds in 5 s (1 bad; 2% > 0%)')
    assert assess(clean(bad_clouds=10, overtaken=16)) == (
        ERROR, 'dropped 26 of 50 clouds in 5 s (10 bad, 16 overtaken; 52% > 50%)')
    assert assess(clean(overtaken=25))[0] == WARN  # exactly half
    # only bad clouds came: all of the input is dropped
    assert assess(clean(clouds=1, bad_clouds=1, detections=0, latency_p95_ms=None))[0] == ERROR


def test_latency_p95_warns_then_errors():
    assert assess(clean(latency_p95_ms=150.0))[0] == OK
    assert assess(clean(latency_p95_ms=180.0)) == (WARN, 'latency p95 180 ms (> 150 ms)')
    assert assess(clean(latency_p95_ms=1500.0)) == (ERROR, 'latency p95 1500 ms (> 1000 ms)')


def test_odometry_bad_odometry_and_failed_detections():
    assert assess(clean(), odometry_stopped=True) == (
        WARN, 'odometry stopped: detecting per sweep')
    assert assess(clean(bad_odometry=2)) == (WARN, '2 bad odometry messages dropped')
    assert assess(clean(detection_errors=1)) == (WARN, '1 detections failed')
    assert assess(clean(detection_errors=3, detections=0, latency_p95_ms=None)) == (
        ERROR, '3 detections failed')


def test_the_worst_level_wins_and_every_tripped_threshold_is_named():
    level, message = assess(clean(latency_p95_ms=2000.0, bad_clouds=1), odometry_stopped=True)
    assert level == ERROR
    assert message.split('; ')[0].startswith('dropped 1 of 50')
    assert 'latency p95 2000 ms (> 1000 ms)' in message
    assert message.endswith('odometry stopped: detecting per sweep')


def sweep(stats: NodeStats, t: float, k: int, detect: bool = True,
          latency: float = 0.06) -> None:
    """Sweep k (stamp k x 100 ms) arrives at t and, if detect, its lanes go out `latency` later."""
    stats.cloud_received(t)
    stats.cloud_ingested(k * SWEEP_NS, t, t + 0.002)
    if detect:
        stats.detection_done(k * SWEEP_NS, t + 0.003, t + 0.01, t + latency - 0.005,
                             t + latency)


def status(stats: NodeStats, now: float, odometry_stopped: bool = False) -> DiagnosticStatus:
    return stats.status({}, 'RELIABLE', 'test', odometry_stopped, now=now)


def test_one_bad_cloud_warns_until_it_leaves_the_window():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    assert status(stats, 0.5).message == 'no clouds received yet'
    for k in range(100):  # 10 s of 10 Hz sweeps, a bad cloud at 2.05 s
        t = 0.1 * k
        sweep(stats, t, k)
        if k == 20:
            stats.cloud_received(t + 0.05)
            stats.error('bad_clouds', ValueError('truncated'), now=t + 0.05)
        if k == 30:
            warned = status(stats, t + 0.01)
            assert (warned.level, warned.message) == (
                WARN, 'dropped 1 of 32 clouds in 3 s (1 bad; 3% > 0%)')
        if k == 71:  # 7.1 s: the bad cloud at 2.05 s is older than the 5 s window
            recovered = status(stats, t + 0.01)
            assert (recovered.level, recovered.message) == (OK, 'running')
    values = {kv.key: kv.value for kv in status(stats, 9.95).values}
    assert (values['bad_clouds'], values['clouds_received']) == ('1', '101')  # lifetime
    assert values['last_error'] == 'bad_clouds: truncated'
    assert (values['window_clouds_dropped'], values['cloud_rate_hz']) == ('0', '10.00')
    assert values['window_latency_ms_p95'] == '60.0'


def test_slow_detections_warn_until_the_window_is_fast_again():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    for k in range(80):
        sweep(stats, 0.1 * k, k, latency=0.3 if k < 20 else 0.06)
        if k == 39:
            assert status(stats, 3.95).message == 'latency p95 300 ms (> 150 ms)'
    assert status(stats, 7.95).level == OK  # only the fast ones are left in the window
    assert stats.window(7.95).latency_p95_ms == pytest.approx(60.0)


def test_input_that_stops_goes_stale_and_recovers_when_it_resumes():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    for k in range(10):
        sweep(stats, 0.1 * k, k)
    assert status(stats, 1.0).level == OK
    assert (status(stats, 4.0).level, status(stats, 4.0).message) == (
        WARN, 'input stale: no clouds for 3.1 s (> 2 s)')
    assert status(stats, 12.0).level == ERROR
    sweep(stats, 12.5, 125)
    assert status(stats, 12.6).level == OK


def test_due_sweeps_a_busy_detector_passed_over_are_dropped():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    sweep(stats, 0.0, 0)
    sweep(stats, 0.1, 1, detect=False)  # came while the detector was busy, then overtaken
    sweep(stats, 0.2, 2, detect=False)
    sweep(stats, 0.3, 3)
    assert stats.counts['sweeps_overtaken'] == 2
    assert status(stats, 0.5).message == (
        'dropped 2 of 4 clouds in 0.5 s (2 overtaken; 50% > 0%)')
    for k in range(4, 60):  # the detector keeps up again
        sweep(stats, 0.1 * k, k)
    assert (status(stats, 5.95).level, status(stats, 5.95).message) == (OK, 'running')


def test_sweeps_left_out_by_rate_hz_or_a_bag_loop_are_not_dropped():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    for k in range(20):  # a 20 Hz sensor at rate_hz 10: every other sweep is not due
        stats.cloud_received(0.05 * k)
        stats.cloud_ingested(k * SWEEP_NS // 2, 0.05 * k, 0.05 * k + 0.002)
        if k % 2 == 0:
            stats.detection_done(k * SWEEP_NS // 2, 0.05 * k, 0.05 * k + 0.01,
                                 0.05 * k + 0.02, 0.05 * k + 0.03)
    sweep(stats, 1.0, 3)  # a stamp going back: the bag started over
    assert stats.counts['sweeps_overtaken'] == 0
    assert (status(stats, 1.1).level, status(stats, 1.1).message) == (OK, 'running')


def test_a_sweep_that_waited_out_its_odometry_is_not_a_latency_problem():
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    sweep(stats, 0.0, 0)
    stats.cloud_received(0.1)
    stats.cloud_ingested(SWEEP_NS, 0.1, 0.102)
    stats.detection_done(SWEEP_NS, 1.1, 1.11, 1.15, 1.16, odometry_timed_out=True)  # 1.06 s
    assert stats.window(1.2).latency_p95_ms == pytest.approx(60.0)
    assert status(stats, 1.2, odometry_stopped=True).message == (
        'odometry stopped: detecting per sweep')
    assert max(stats.latencies_ms) == pytest.approx(1060.0)  # still in latency_ms_p95


def test_clouds_and_poses_dds_lost_warn_and_lost_clouds_are_drops():
    # DDS reports them lost (best-effort clouds over a small shared-memory segment, poses
    # overrun by the cloud published after them); the node never saw them
    assert assess(clean(clouds=20, lost=30)) == (
        ERROR, 'dropped 30 of 50 clouds in 5 s (30 lost by DDS; 60% > 50%)')
    assert assess(clean(odometry_lost=3)) == (
        WARN, "DDS lost 3 odometry messages (a publisher's shared-memory segment overrun by "
              'large messages: see the README on DDS)')
    stats = NodeStats(MIN_INTERVAL_NS, now=0.0)
    for k in range(30):
        sweep(stats, 0.1 * k, k)
    stats.lost_in_transport('clouds', 4, now=2.95)
    stats.lost_in_transport('odometry', 2, now=2.95)
    warned = status(stats, 3.0)
    assert warned.level == WARN
    assert 'dropped 4 of 34 clouds in 3 s (4 lost by DDS' in warned.message
    assert 'DDS lost 2 odometry messages' in warned.message
    values = {kv.key: kv.value for kv in warned.values}
    assert (values['clouds_lost_in_dds'], values['odometry_lost_in_dds']) == ('4', '2')
    assert values['window_clouds_dropped'] == '4'
    assert 'lost' not in status(stats, 8.5).message  # out of the window
