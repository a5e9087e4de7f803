"""What camera_lane_detector reports on /diagnostics: a level from the last few seconds, the
pipeline's counters, rates, latency percentiles and stage medians.

As lane_detector's (ros/diagnostics.py, whose Thresholds it shares): OK, WARN or ERROR judged
only on the last window_sec seconds, every tripped threshold named, 'running' when none is.
Drops are bad images, images overtaken (due, but a newer one came before the detector was free)
and images DDS lost on the way; images left out on purpose (a 30 Hz camera at rate_hz 10) are
not drops. latency_ms = image arrival (its callback) -> its lanes published. Stage medians (ms):
image_decode = message -> array, wait = arrival -> detection start, warp / model / decode =
SaladDetector's stages, output = frames, ids and outline, publish = the three messages.
Times are time.monotonic() seconds, and every method takes `now`, so tests need no sleeping.
"""
from __future__ import annotations

import collections
import time
from collections.abc import Mapping

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from fhld_ros.ros.diagnostics import THRESHOLDS, Thresholds

STATUS_NAME = 'fhld_ros: camera_lane_detector'
STAGES = ('image_decode', 'wait', 'warp', 'model', 'decode', 'output', 'publish')
HISTORY = 300  # recent detections the medians and percentiles cover
ARRIVALS_KEPT = 20  # arrival times of images waiting for detection (one at a time waits)
EVENTS_KEPT = 10_000  # per kind in the window: a flood of bad images cannot grow memory
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
DROPS = ('bad_images', 'images_overtaken', 'images_lost')


def _tripped(value: float, warn: float, error: float) -> tuple[bytes, float] | None:
    if value > error:
        return ERROR, error
    return (WARN, warn) if value > warn else None


class CameraStats:
    """Counts, drops and timings of the camera node, summed up as one DiagnosticStatus."""

    def __init__(self, thresholds: Thresholds | None = None, now: float | None = None) -> None:
        self.started = time.monotonic() if now is None else now
        self.th = thresholds or THRESHOLDS
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_error = ''
        self.arrived_at: dict[int, float] = {}  # image stamp (ns) -> arrival
        self.latencies_ms: collections.deque[float] = collections.deque(maxlen=HISTORY)
        self.stages_ms = {name: collections.deque(maxlen=HISTORY) for name in STAGES}
        self.last_image: float | None = None
        self.recent: dict[str, collections.deque[tuple[float, float]]] = \
            collections.defaultdict(lambda: collections.deque(maxlen=EVENTS_KEPT))

    def event(self, kind: str, now: float | None = None, value: float = 1.0) -> None:
        """Something that happened now: images_received, a drop kind (DROPS), detections
        (value: latency ms), bad_camera_info, detection_errors."""
        self.recent[kind].append((time.monotonic() if now is None else now, value))

    def image_received(self, now: float) -> None:
        """Any image message, before it is decoded (a bad one too: the input is not stale)."""
        self.counts['images_received'] += 1
        self.last_image = now
        self.event('images_received', now)

    def error(self, what: str, exc: Exception, now: float | None = None) -> None:
        """Count a failure under `what` and keep its message for the next status."""
        self.counts[what] += 1
        self.last_error = f'{what}: {exc}'
        self.event(what, now)

    def image_due(self, stamp_ns: int, arrived: float, decode_ms: float) -> None:
        self.stages_ms['image_decode'].append(decode_ms)
        self.arrived_at[stamp_ns] = arrived
        if len(self.arrived_at) > ARRIVALS_KEPT:
            self.arrived_at.pop(next(iter(self.arrived_at)))

    def detection_done(self, stamp_ns: int, start: float, timings_ms: Mapping[str, float],
                       done: float, publish_ms: float) -> None:
        arrived = self.arrived_at.pop(stamp_ns, None)
        latency = float('nan')
        if arrived is not None:
            latency = (done - arrived) * 1e3
            self.latencies_ms.append(latency)
            self.stages_ms['wait'].append((start - arrived) * 1e3)
        for name in ('warp', 'model', 'decode', 'output'):
            if f'{name}_ms' in timings_ms:
                self.stages_ms[name].append(timings_ms[f'{name}_ms'])
        self.stages_ms['publish'].append(publish_ms)
        self.event('detections', done, latency)

    def _recent(self, kind: str, now: float) -> list[float]:
        events = self.recent[kind]
        while events and events[0][0] < now - self.th.window_sec:
            events.popleft()
        return [value for _, value in events]

    def assess(self, now: float) -> tuple[bytes, str, dict[str, str]]:
        """(level, message, window values) of the last window_sec seconds."""
        seconds = max(min(self.th.window_sec, now - self.started), 1e-9)
        images = len(self._recent('images_received', now))
        drops = {kind: int(sum(self._recent(kind, now))) for kind in DROPS}
        detected = self._recent('detections', now)
        latencies = [v for v in detected if not np.isnan(v)]
        found: list[tuple[bytes, str]] = []
        since = None if self.last_image is None else now - self.last_image
        if since is None:
            found.append((WARN, 'no images received yet'))
        elif tripped := _tripped(since, self.th.stale_warn_sec, self.th.stale_error_sec):
            found.append((tripped[0], f'input stale: no images for {since:.1f} s '
                                      f'(> {tripped[1]:g} s)'))
        dropped, sent = sum(drops.values()), images + drops['images_lost']
        rate = dropped / max(sent, dropped, 1)
        if tripped := _tripped(rate, self.th.drop_rate_warn, self.th.drop_rate_error):
            kinds = ', '.join(f'{n} {kind.replace("images_", "").replace("_images", "")}'
                              for kind, n in drops.items() if n)
            found.append((tripped[0], f'dropped {dropped} of {sent} images in {seconds:.2g} s '
                                      f'({kinds}; {rate:.0%} > {tripped[1]:.0%})'))
        p95 = float(np.percentile(latencies, 95)) if latencies else None
        if p95 is not None and (tripped := _tripped(p95, self.th.latency_p95_warn_ms,
                                                    self.th.latency_p95_error_ms)):
            found.append((tripped[0], f'latency p95 {p95:.0f} ms (> {tripped[1]:g} ms)'))
        if bad_info := len(self._recent('bad_camera_info', now)):
            found.append((WARN, f'{bad_info} bad camera_info messages'))
        if errors := len(self._recent('detection_errors', now)):
            found.append((WARN if detected else ERROR, f'{errors} detections failed'))
        values = {'image_rate_hz': f'{images / seconds:.2f}',
                  'detection_rate_hz': f'{len(detected) / seconds:.2f}',
                  'window_sec': f'{seconds:.1f}', 'window_images_dropped': str(dropped)}
        if p95 is not None:
            values['window_latency_ms_p95'] = f'{p95:.1f}'
        if since is not None:
            values['seconds_since_image'] = f'{since:.1f}'
        level = max((level for level, _ in found), default=OK)
        return level, '; '.join(message for _, message in found) or 'running', values

    def status(self, pipeline_counters: Mapping[str, int], input_reliability: str,
               hardware_id: str, now: float | None = None) -> DiagnosticStatus:
        """The level and message of the last window (assess), counters since start, timings."""
        now = time.monotonic() if now is None else now
        level, message, window = self.assess(now)
        values = {k: str(v) for k, v in sorted(dict(pipeline_counters, **self.counts).items())}
        values.update(window)
        if self.latencies_ms:
            p50, p95 = np.percentile(np.asarray(self.latencies_ms), [50, 95])
            values['latency_ms_p50'], values['latency_ms_p95'] = f'{p50:.1f}', f'{p95:.1f}'
        for name, times in self.stages_ms.items():
            if times:
                values[f'stage_{name}_ms_p50'] = f'{np.median(np.asarray(times)):.1f}'
        values['input_reliability'] = input_reliability
        values['last_error'] = self.last_error
        return DiagnosticStatus(level=level, name=STATUS_NAME, hardware_id=hardware_id,
                                message=message,
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])
