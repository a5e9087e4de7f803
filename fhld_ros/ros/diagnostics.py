"""What lane_detector reports on /diagnostics: a level from the last few seconds, counters,
rates, latency and stage medians.

The level follows diagnostic_updater's convention: OK, WARN or ERROR, judged only on what
happened in the last THRESHOLDS.window_sec seconds (never on lifetime counters, so one bad
message does not leave the node in WARN forever), and the message names every threshold that
tripped; 'running' when none did. Thresholds lists them all.

Stage breakdown (medians, ms): ingest = cloud callback (decode + insert), wait = sweep arrival
-> its detection starts, raster = window raster, detect = model and tracking, publish = /lanes
+ ego paths. latency_ms = sweep arrival -> its lanes published. Times are time.monotonic()
seconds; the node records them, this module keeps the numbers out of the node, and every
method takes `now` so tests can replay a timeline without sleeping.
"""
from __future__ import annotations

import collections
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

STAGES = ('ingest', 'wait', 'raster', 'detect', 'publish')
HISTORY = 300  # recent sweeps / detections the medians and percentiles cover
ARRIVALS_KEPT = 100  # arrival times of sweeps not detected yet (most are skipped at 10 Hz)
EVENTS_KEPT = 10_000  # per kind in the window: a flood of bad clouds cannot grow memory
STATUS_NAME = 'fhld_ros: lane_detector'
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


@dataclass(frozen=True)
class Thresholds:
    """When /diagnostics leaves OK; everything is measured over the last window_sec seconds.

    - latency: 95th percentile of sweep arrival -> its lanes published. WARN above the README's
      target (150 ms); ERROR a second behind, when the lanes describe where the car was.
      Sweeps detected while odometry is stopped are left out: the first of them waited out
      odom_wait_sec on purpose, and the odometry WARN says so.
    - drop rate: dropped / sent clouds, where dropped = bad clouds (malformed, too large,
      no frame_id) + sweeps overtaken (due for a detection by rate_hz, but a newer sweep was
      detected instead because the detector was busy) + clouds DDS lost on the way (it says
      so for a best-effort subscription), and sent = received + lost. Any drop is a WARN; over
      half an ERROR.
      Sweeps left out on purpose (a 20 Hz sensor at rate_hz 10) are not drops.
    - stale input: no cloud at all for this long (a 10 Hz sensor misses 20 sweeps in 2 s);
      before the first cloud the node WARNs that it waits for one.
    Clouds or poses that DDS reports lost on the way are a WARN (lost clouds count as drops).
    A level trips when its value is above the threshold. Odometry that stopped (sweeps
    detected alone in the cloud frame) is a WARN for as long as it stays stopped: the pipeline
    knows when it comes back. Bad odometry in the window is a WARN; failed detections a WARN,
    or an ERROR when none succeeded in the window.
    """

    window_sec: float = 5.0
    latency_p95_warn_ms: float = 150.0
    latency_p95_error_ms: float = 1000.0
    drop_rate_warn: float = 0.0
    drop_rate_error: float = 0.5
    stale_warn_sec: float = 2.0
    stale_error_sec: float = 10.0


THRESHOLDS = Thresholds()


@dataclass(frozen=True)
class WindowSummary:
    """What happened in the last window_sec seconds (`seconds`: less right after start-up)."""

    seconds: float
    clouds: int = 0  # received, good or bad
    bad_clouds: int = 0
    overtaken: int = 0
    lost: int = 0  # clouds DDS lost before they reached the node
    bad_odometry: int = 0
    odometry_lost: int = 0  # poses DDS lost before they reached the node
    detections: int = 0
    detection_errors: int = 0
    latency_p95_ms: float | None = None
    since_cloud: float | None = None  # seconds since the newest cloud; None before the first

    @property
    def dropped(self) -> int:
        """Clouds that never gave lanes of their own: bad, overtaken or lost by DDS."""
        return self.bad_clouds + self.overtaken + self.lost


def _tripped(value: float, warn: float, error: float) -> tuple[bytes, float] | None:
    """(ERROR, error) when value is above error, (WARN, warn) above warn, else None."""
    if value > error:
        return ERROR, error
    return (WARN, warn) if value > warn else None


def input_problems(noun: str, since: float | None, drops: Mapping[str, int], sent: int,
                   seconds: float, p95: float | None,
                   th: Thresholds = THRESHOLDS) -> list[tuple[bytes, str]]:
    """(level, message) of each input threshold tripped, for either node: stale or no input
    (`noun`: clouds, images), drops (`drops`: label -> count, of `sent` messages) and latency."""
    found: list[tuple[bytes, str]] = []
    if since is None:
        found.append((WARN, f'no {noun} received yet'))
    elif tripped := _tripped(since, th.stale_warn_sec, th.stale_error_sec):
        found.append((tripped[0], f'input stale: no {noun} for {since:.1f} s '
                                  f'(> {tripped[1]:g} s)'))
    dropped = sum(drops.values())
    rate = dropped / max(sent, dropped, 1)
    if tripped := _tripped(rate, th.drop_rate_warn, th.drop_rate_error):
        kinds = ', '.join(f'{n} {label}' for label, n in drops.items() if n)
        found.append((tripped[0], f'dropped {dropped} of {sent} {noun} in {seconds:.2g} s '
                                  f'({kinds}; {rate:.0%} > {tripped[1]:.0%})'))
    if p95 is not None and (tripped := _tripped(p95, th.latency_p95_warn_ms,
                                                th.latency_p95_error_ms)):
        found.append((tripped[0], f'latency p95 {p95:.0f} ms (> {tripped[1]:g} ms)'))
    return found


def verdict(found: list[tuple[bytes, str]]) -> tuple[bytes, str]:
    """The worst level found, and every message; (OK, 'running') when none."""
    level = max((level for level, _ in found), default=OK)
    return level, '; '.join(message for _, message in found) or 'running'


def assess(window: WindowSummary, odometry_stopped: bool = False,
           th: Thresholds = THRESHOLDS) -> tuple[bytes, str]:
    """(level, message) of a window: the worst tripped threshold, and all of them named."""
    found = input_problems('clouds', window.since_cloud, {
        'bad': window.bad_clouds, 'overtaken': window.overtaken, 'lost by DDS': window.lost},
        window.clouds + window.lost, window.seconds, window.latency_p95_ms, th)
    if odometry_stopped:
        found.append((WARN, 'odometry stopped: detecting per sweep'))
    if window.bad_odometry:
        found.append((WARN, f'{window.bad_odometry} bad odometry messages dropped'))
    if window.odometry_lost:
        found.append((WARN, f'DDS lost {window.odometry_lost} odometry messages (a publisher\'s '
                            'shared-memory segment overrun by large messages: see the README '
                            'on DDS)'))
    if window.detection_errors:
        found.append((WARN if window.detections else ERROR,
                      f'{window.detection_errors} detections failed'))
    return verdict(found)


class WindowedStats:
    """What both nodes' stats share: counters since start, the last error, events counted over
    the last window_sec seconds, input arrivals, latency percentiles and stage medians."""

    def __init__(self, stages: tuple[str, ...], arrivals_kept: int,
                 thresholds: Thresholds | None = None, now: float | None = None) -> None:
        self.started = time.monotonic() if now is None else now
        self.thresholds = thresholds or THRESHOLDS
        self.arrivals_kept = arrivals_kept
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_error = ''
        self.arrived_at: dict[int, float] = {}  # input stamp (ns) -> arrival
        self.latencies_ms: collections.deque[float] = collections.deque(maxlen=HISTORY)
        self.stages_ms = {name: collections.deque(maxlen=HISTORY) for name in stages}
        # kind -> (time, amount or latency ms), pruned to the window when read
        self.recent: dict[str, collections.deque[tuple[float, float]]] = \
            collections.defaultdict(lambda: collections.deque(maxlen=EVENTS_KEPT))

    def event(self, kind: str, now: float | None = None, value: float = 1.0) -> None:
        """Something that happened at `now` (default: now), counted in the window."""
        self.recent[kind].append((time.monotonic() if now is None else now, value))

    def error(self, what: str, exc: Exception, now: float | None = None) -> None:
        """Count a failure under `what` and keep its message for the next status."""
        self.counts[what] += 1
        self.last_error = f'{what}: {exc}'
        self.event(what, now)

    def arrived(self, stamp_ns: int, at: float) -> None:
        """An input that may be detected arrived at `at` (only the newest few are kept)."""
        self.arrived_at[stamp_ns] = at
        if len(self.arrived_at) > self.arrivals_kept:
            self.arrived_at.pop(next(iter(self.arrived_at)))

    def latency(self, arrived: float | None, start: float, done: float) -> float:
        """Arrival -> published (ms; NaN for an input whose arrival is not known), recorded
        with its wait for the detection to start."""
        if arrived is None:
            return math.nan
        self.latencies_ms.append((done - arrived) * 1e3)
        self.stages_ms['wait'].append((start - arrived) * 1e3)
        return (done - arrived) * 1e3

    def recent_values(self, kind: str, now: float) -> list[float]:
        """The values of the `kind` events in the window ending at `now`."""
        events = self.recent[kind]
        while events and events[0][0] < now - self.thresholds.window_sec:
            events.popleft()
        return [value for _, value in events]

    def window_seconds(self, now: float) -> float:
        """The window's length: less right after start-up."""
        return max(min(self.thresholds.window_sec, now - self.started), 1e-9)

    def all_values(self, counters: Mapping[str, int], window: Mapping[str, str],
                   input_reliability: str) -> dict[str, str]:
        """Key -> value strings: `counters` (since start), the `window`'s values, the
        timings, the input reliability and the last error."""
        values = {k: str(v) for k, v in sorted(counters.items())}
        values.update(window)
        if self.latencies_ms:
            p50, p95 = np.percentile(np.asarray(self.latencies_ms), [50, 95])
            values['latency_ms_p50'], values['latency_ms_p95'] = f'{p50:.1f}', f'{p95:.1f}'
        for name, times in self.stages_ms.items():
            if times:
                values[f'stage_{name}_ms_p50'] = f'{np.median(np.asarray(times)):.1f}'
        values['input_reliability'] = input_reliability
        values['last_error'] = self.last_error
        return values


class NodeStats(WindowedStats):
    """Counts, errors and timings of the node, summed up as one DiagnosticStatus.

    min_interval_ns: the node's least stamp difference between detected sweeps (rate_hz); a
    sweep at least that much newer than the last detected one was due, and is counted as
    overtaken when a newer sweep is detected instead.
    """

    def __init__(self, min_interval_ns: int = 0, thresholds: Thresholds | None = None,
                 now: float | None = None) -> None:
        super().__init__(STAGES, ARRIVALS_KEPT, thresholds, now)
        self.min_interval_ns = min_interval_ns
        self.last_detected_ns: int | None = None
        self.last_cloud: float | None = None

    def cloud_received(self, now: float | None = None) -> None:
        """Any cloud message, before it is decoded (a bad one too: the input is not stale)."""
        now = time.monotonic() if now is None else now
        self.counts['clouds_received'] += 1
        self.last_cloud = now
        self.event('clouds_received', now)

    def lost_in_transport(self, what: str, count: int, now: float | None = None) -> None:
        """`count` more `what` ('clouds', 'odometry') that DDS lost before delivery."""
        self.counts[f'{what}_lost_in_dds'] += count
        self.event(f'{what}_lost', now, count)

    def cloud_ingested(self, stamp_ns: int, arrived: float, done: float) -> None:
        self.stages_ms['ingest'].append((done - arrived) * 1e3)
        self.arrived(stamp_ns, arrived)

    def detection_done(self, stamp_ns: int, start: float, rastered: float, detected: float,
                       done: float, odometry_timed_out: bool = False) -> None:
        """odometry_timed_out: detected while odometry is stopped (the first such sweep waited
        odom_wait_sec for it); its latency is left out of the window's (see Thresholds)."""
        latency = self.latency(self.arrived_at.get(stamp_ns), start, done)
        for name, (a, b) in {'raster': (start, rastered), 'detect': (rastered, detected),
                             'publish': (detected, done)}.items():
            self.stages_ms[name].append((b - a) * 1e3)
        self.event('detections', done, math.nan if odometry_timed_out else latency)
        last, self.last_detected_ns = self.last_detected_ns, stamp_ns
        if last is not None and stamp_ns > last:  # (a stamp going back is a new run)
            due = last + self.min_interval_ns
            overtaken = sum(1 for stamp in self.arrived_at if due <= stamp < stamp_ns)
            if overtaken:
                self.counts['sweeps_overtaken'] += overtaken
                self.event('sweeps_overtaken', done, overtaken)

    def window(self, now: float | None = None) -> WindowSummary:
        now = time.monotonic() if now is None else now
        latencies = [v for v in self.recent_values('detections', now) if not math.isnan(v)]
        return WindowSummary(
            seconds=self.window_seconds(now),
            clouds=len(self.recent_values('clouds_received', now)),
            bad_clouds=len(self.recent_values('bad_clouds', now)),
            overtaken=int(sum(self.recent_values('sweeps_overtaken', now))),
            lost=int(sum(self.recent_values('clouds_lost', now))),
            bad_odometry=len(self.recent_values('bad_odometry', now)),
            odometry_lost=int(sum(self.recent_values('odometry_lost', now))),
            detections=len(self.recent_values('detections', now)),
            detection_errors=len(self.recent_values('detection_errors', now)),
            latency_p95_ms=float(np.percentile(latencies, 95)) if latencies else None,
            since_cloud=None if self.last_cloud is None else now - self.last_cloud)

    def values(self, counters: Mapping[str, int], input_reliability: str,
               window: WindowSummary) -> dict[str, str]:
        """Key -> value strings: `counters` (the pipeline's and the node's, since start), the
        window's rates and drops, the timings."""
        values = {'cloud_rate_hz': f'{window.clouds / window.seconds:.2f}',
                  'detection_rate_hz': f'{window.detections / window.seconds:.2f}',
                  'window_sec': f'{window.seconds:.1f}',
                  'window_clouds_dropped': str(window.dropped)}
        if window.latency_p95_ms is not None:
            values['window_latency_ms_p95'] = f'{window.latency_p95_ms:.1f}'
        if window.since_cloud is not None:
            values['seconds_since_cloud'] = f'{window.since_cloud:.1f}'
        return self.all_values(counters, values, input_reliability)

    def status(self, pipeline_counters: Mapping[str, int], input_reliability: str,
               hardware_id: str, odometry_stopped: bool = False,
               now: float | None = None) -> DiagnosticStatus:
        """The level and message of the last window_sec seconds (assess), and the values."""
        window = self.window(now)
        level, message = assess(window, odometry_stopped, self.thresholds)
        values = self.values(dict(pipeline_counters, **self.counts), input_reliability, window)
        values['odometry_stopped'] = str(odometry_stopped).lower()
        return DiagnosticStatus(level=level, name=STATUS_NAME, hardware_id=hardware_id,
                                message=message,
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])
