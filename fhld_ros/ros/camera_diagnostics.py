"""What camera_lane_detector reports on /diagnostics: a level from the last few seconds, the
pipeline's counters, rates, latency percentiles and stage medians.

As lane_detector's (ros/diagnostics.py, whose Thresholds, windowed counting and timings it
shares): OK, WARN or ERROR judged only on the last window_sec seconds, every tripped threshold
named, 'running' when none is.
Drops are bad images, images overtaken (due, but a newer one came before the detector was free)
and images DDS lost on the way; images left out on purpose (a 30 Hz camera at rate_hz 10) are
not drops; nor are lanes_unpainted, the decoded lanes the paint check dropped
(salad/paint_evidence.py: along kerbs, not paint), counted since start. latency_ms = image
arrival (its callback) -> its lanes published. Stage medians (ms):
image_decode = message -> array, wait = arrival -> detection start, warp / model / decode =
SaladDetector's stages, output = frames, ids and outline, publish = the three messages.
window_lanes_plane_height_m: the median height of the camera over the plane its lanes span;
window_lanes_pitch_deg: the median of its pitch down where its lanes' image lines meet (both
the image's own read of the mount, to check camera_to_output against).
Times are time.monotonic() seconds, and every method takes `now`, so tests need no sleeping.
"""
from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from fhld_ros.ros.diagnostics import (
    ERROR,
    WARN,
    Thresholds,
    WindowedStats,
    input_problems,
    verdict,
)

STATUS_NAME = 'fhld_ros: camera_lane_detector'
STAGES = ('image_decode', 'wait', 'warp', 'model', 'decode', 'output', 'publish')
ARRIVALS_KEPT = 20  # arrival times of images waiting for detection (one at a time waits)
# drop kinds -> how the status message names them
DROPS = {'bad_images': 'bad', 'images_overtaken': 'overtaken', 'images_lost': 'lost'}


class CameraStats(WindowedStats):
    """Counts, drops and timings of the camera node, summed up as one DiagnosticStatus.

    Events (`event`): images_received, a drop kind (DROPS), detections (value: latency ms),
    bad_camera_info, detection_errors.
    """

    def __init__(self, thresholds: Thresholds | None = None, now: float | None = None) -> None:
        super().__init__(STAGES, ARRIVALS_KEPT, thresholds, now)
        self.last_image: float | None = None

    def image_received(self, now: float) -> None:
        """Any image message, before it is decoded (a bad one too: the input is not stale)."""
        self.counts['images_received'] += 1
        self.last_image = now
        self.event('images_received', now)

    def image_due(self, stamp_ns: int, arrived: float, decode_ms: float) -> None:
        self.stages_ms['image_decode'].append(decode_ms)
        self.arrived(stamp_ns, arrived)

    def detection_done(self, stamp_ns: int, start: float, timings_ms: Mapping[str, float],
                       done: float, publish_ms: float,
                       lanes_plane_height_m: float | None = None,
                       lanes_pitch_deg: float | None = None) -> None:
        """lanes_plane_height_m, lanes_pitch_deg: the camera's height over the plane its lanes
        span and its pitch where their image lines meet, as LaneOutput has them (None: none)."""
        latency = self.latency(self.arrived_at.pop(stamp_ns, None), start, done)
        for name in ('warp', 'model', 'decode', 'output'):
            if f'{name}_ms' in timings_ms:
                self.stages_ms[name].append(timings_ms[f'{name}_ms'])
        self.stages_ms['publish'].append(publish_ms)
        self.event('detections', done, latency)
        if lanes_plane_height_m is not None:
            self.event('lanes_plane_height_m', done, lanes_plane_height_m)
        if lanes_pitch_deg is not None:
            self.event('lanes_pitch_deg', done, lanes_pitch_deg)

    def assess(self, now: float) -> tuple[bytes, str, dict[str, str]]:
        """(level, message, window values) of the last window_sec seconds."""
        seconds = self.window_seconds(now)
        images = len(self.recent_values('images_received', now))
        drops = {kind: int(sum(self.recent_values(kind, now))) for kind in DROPS}
        detected = self.recent_values('detections', now)
        latencies = [v for v in detected if not np.isnan(v)]
        since = None if self.last_image is None else now - self.last_image
        p95 = float(np.percentile(latencies, 95)) if latencies else None
        found = input_problems('images', since,
                               {DROPS[kind]: n for kind, n in drops.items()},
                               images + drops['images_lost'], seconds, p95, self.thresholds)
        if bad_info := len(self.recent_values('bad_camera_info', now)):
            found.append((WARN, f'{bad_info} bad camera_info messages'))
        if errors := len(self.recent_values('detection_errors', now)):
            found.append((WARN if detected else ERROR, f'{errors} detections failed'))
        values = {'image_rate_hz': f'{images / seconds:.2f}',
                  'detection_rate_hz': f'{len(detected) / seconds:.2f}',
                  'window_sec': f'{seconds:.1f}',
                  'window_images_dropped': str(sum(drops.values()))}
        if p95 is not None:
            values['window_latency_ms_p95'] = f'{p95:.1f}'
        if since is not None:
            values['seconds_since_image'] = f'{since:.1f}'
        # the network's own read of its mount: far from the camera's real height, every depth
        # is off by as much (a real camera read 35 % high, docs/salad.md); give road_plane_m
        if heights := self.recent_values('lanes_plane_height_m', now):
            values['window_lanes_plane_height_m'] = f'{np.median(heights):.2f}'
        if pitches := self.recent_values('lanes_pitch_deg', now):
            values['window_lanes_pitch_deg'] = f'{np.median(pitches):.2f}'
        return (*verdict(found), values)

    def status(self, pipeline_counters: Mapping[str, int], input_reliability: str,
               hardware_id: str, now: float | None = None) -> DiagnosticStatus:
        """The level and message of the last window (assess), counters since start, timings."""
        now = time.monotonic() if now is None else now
        level, message, window = self.assess(now)
        values = self.all_values(dict(pipeline_counters, **self.counts), window,
                                 input_reliability)
        return DiagnosticStatus(level=level, name=STATUS_NAME, hardware_id=hardware_id,
                                message=message,
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])
