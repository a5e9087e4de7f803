"""What lane_detector reports on /diagnostics: counters, rates, latency and stage medians.

Stage breakdown (medians, ms): ingest = cloud callback (decode + insert), wait = sweep arrival
-> its detection starts, raster = window raster, detect = model and tracking, publish = /lanes
+ ego paths. latency_ms = sweep arrival -> its lanes published. Times are time.monotonic()
seconds; the node records them, this module keeps the numbers out of the node.
"""
from __future__ import annotations

import collections
import time
from collections.abc import Mapping

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

STAGES = ('ingest', 'wait', 'raster', 'detect', 'publish')
HISTORY = 300  # recent sweeps / detections the medians and percentiles cover
ARRIVALS_KEPT = 100  # arrival times of sweeps not detected yet (most are skipped at 10 Hz)
STATUS_NAME = 'fhld_ros: lane_detector'


class NodeStats:
    """Counts, errors and timings of the node, summed up as one DiagnosticStatus."""

    def __init__(self) -> None:
        self.started = time.monotonic()
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_error = ''
        self.arrived_at: dict[int, float] = {}  # sweep stamp (ns) -> arrival
        self.latencies_ms: collections.deque[float] = collections.deque(maxlen=HISTORY)
        self.stages_ms = {name: collections.deque(maxlen=HISTORY) for name in STAGES}

    def error(self, what: str, exc: Exception) -> None:
        """Count a failure under `what` and keep its message for the next status."""
        self.counts[what] += 1
        self.last_error = f'{what}: {exc}'

    def cloud_ingested(self, stamp_ns: int, arrived: float, done: float) -> None:
        self.stages_ms['ingest'].append((done - arrived) * 1e3)
        self.arrived_at[stamp_ns] = arrived
        if len(self.arrived_at) > ARRIVALS_KEPT:
            self.arrived_at.pop(next(iter(self.arrived_at)))

    def detection_done(self, stamp_ns: int, start: float, rastered: float, detected: float,
                       done: float) -> None:
        arrived = self.arrived_at.get(stamp_ns)
        if arrived is not None:
            self.latencies_ms.append((done - arrived) * 1e3)
            self.stages_ms['wait'].append((start - arrived) * 1e3)
        for name, (a, b) in {'raster': (start, rastered), 'detect': (rastered, detected),
                             'publish': (detected, done)}.items():
            self.stages_ms[name].append((b - a) * 1e3)

    def values(self, counters: Mapping[str, int], input_reliability: str) -> dict[str, str]:
        """Key -> value strings: `counters` (the pipeline's and the node's) and the timings."""
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
        values['input_reliability'] = input_reliability
        values['last_error'] = self.last_error
        return values

    def status(self, pipeline_counters: Mapping[str, int], input_reliability: str,
               hardware_id: str, odometry_stopped: bool = False) -> DiagnosticStatus:
        """WARN once a bad message was dropped or anything failed, or while sweeps go in
        without odometry (it stopped), else OK."""
        counters = dict(pipeline_counters, **self.counts)
        dropped = counters.get('bad_clouds', 0) + counters.get('bad_odometry', 0)
        values = self.values(counters, input_reliability)
        values['odometry_stopped'] = str(odometry_stopped).lower()
        messages = ([f'{dropped} bad messages dropped'] if dropped else []) + (
            ['odometry stopped: detecting per sweep'] if odometry_stopped else [])
        warn = dropped or self.last_error or odometry_stopped
        return DiagnosticStatus(
            level=DiagnosticStatus.WARN if warn else DiagnosticStatus.OK,
            name=STATUS_NAME, hardware_id=hardware_id,
            message='; '.join(messages) or 'running',
            values=[KeyValue(key=k, value=v) for k, v in values.items()])
