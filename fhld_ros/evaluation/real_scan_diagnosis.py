"""`fhld realscans --explain`: per labelled line of the real sweeps, the measured facts that say
why the detector finds it or misses it (docs/real_scans.md).

Every sweep goes once through the node's path (real_scans.detect_sweep) at gain 1 with a
detector that keeps its unfiltered output: the model's lanes down to LOW_THRESHOLD without the
evidence checks. The node's lanes follow from them exactly (each lane is scored and checked on
its own), so one model run gives the published lanes, the candidates, and what the score
threshold and each check do to the best candidate on a line. Per line:

* found: >= 50 % of the line within 0.3 m of a published lane (the scorer's coverage);
* returns / rings: ground returns within NEAR_M (top view) of the line, and how many lasers they
  come from (the sweep's ring column, else elevation clusters as the contrast_rings encoding
  forms rings: intensity_rings.elevation_ring_ids);
* contrast: median encoded intensity of those returns / that of the ground BESIDE_M to either
  side, under the checkpoint's encoding (and under `contrast` when that differs);
* ring spread: std across rings of each ring's median log raw intensity beside the line;
* best: the highest confidence of a candidate covering >= 50 % of the line; paint / evidence:
  whether that candidate survives the paint check / the evidence cut alone;
* verdict: found, paint-check (confident enough, removed by a check), low-score (below the
  node's score_threshold), no-candidate (the model draws nothing on the line).

This module does not import real_scans (which imports it for its command line): the scorer's
coverage and the node path come in as a Scoring.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from fhld_ros.detectors import classical_detector, fhld_detections, with_evidence
from fhld_ros.importing.pcd import cloud_points
from fhld_ros.intensity import ABSOLUTE, CONTRAST, IntensityEncoder, ground_mask
from fhld_ros.intensity_rings import elevation_ring_ids
from fhld_ros.parameters import DetectorParams
from fhld_ros.rolling_grid import BevWindow

LOW_THRESHOLD = 0.2  # candidates: the model's lanes down to this confidence
SHARE = 0.5  # as the scorer: a lane is on a line when it covers this share of it
NEAR_M = 0.15  # returns on the line (paint is 0.1-0.2 m wide, labels 3-8 cm off it)
BESIDE_M = (0.4, 1.0)  # the road to either side, clear of the paint
# ground: this close in height to the label (its z is the road's), so curb faces and tops, cars
# and vegetation beside the line do not count as road
LEVEL_M = 0.1
MIN_RING_RETURNS = 5  # a ring's median beside the line needs this many returns
CROP_M = (16.0, 8.0)  # the figure's top-view crop around a line, along x and y
VERDICTS = ('found', 'paint-check', 'low-score', 'no-candidate')


@dataclass(frozen=True)
class Scoring:
    """What the diagnosis borrows from real_scans: coverage(line, lanes, half) and
    detect_sweep(params, detector, points) (the node's path for one sweep)."""

    coverage: Callable[[np.ndarray, list[np.ndarray], float], float]
    detect_sweep: Callable[..., tuple[list[np.ndarray], np.ndarray]]


@dataclass
class LineFacts:
    file: str
    sensor: str
    line: str
    found: bool
    returns: int  # ground returns within NEAR_M of the line
    rings: int  # distinct rings among them
    contrast: float | None  # under the checkpoint's encoding
    contrast_plain: float | None  # under `contrast`, when the checkpoint's encoding differs
    ring_spread: float | None  # std of per-ring median log raw intensity beside the line
    best: float | None  # best confidence of a candidate on the line
    paint: str  # the best candidate after the paint check alone: kept / dropped / -
    evidence: str  # after the evidence cut alone: kept / cut / -
    verdict: str


@dataclass
class SweepDiagnosis:
    """One sweep's facts and what the figure draws: ground points, encoded intensity, lanes."""

    file: str
    xyz: np.ndarray  # (N, 3) sensor frame
    encoded: np.ndarray  # (N,) the checkpoint's encoding
    candidates: list[np.ndarray]  # (K, 3) sensor frame, confidence >= LOW_THRESHOLD
    confidences: np.ndarray
    lines: list[tuple[np.ndarray, LineFacts]]  # label polyline, facts


class _Capture:
    """A LaneDetector keeping its window and unfiltered output (the pipeline filters a copy)."""

    def __init__(self, detect: Callable[[BevWindow], tuple[list[np.ndarray], np.ndarray]],
                 intensity_encoding: str) -> None:
        self.detect, self.intensity_encoding = detect, intensity_encoding
        self.window: BevWindow | None = None
        self.output: tuple[list[np.ndarray], np.ndarray] = ([], np.zeros(0))

    def __call__(self, window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]:
        self.window, self.output = window, self.detect(window)
        return self.output


def capture_detector(params: DetectorParams) -> _Capture:
    """The detector of params down to LOW_THRESHOLD, without evidence checks."""
    if params.detector == 'classical':
        return _Capture(classical_detector(), ABSOLUTE)
    detections = fhld_detections(dataclasses.replace(params, score_threshold=LOW_THRESHOLD))

    def detect(window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]:
        found = detections(window)
        return found.lanes, np.asarray(found.confidences, dtype=np.float64)
    return _Capture(detect, detections.intensity_encoding)


def line_frame(xy: np.ndarray, polyline: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per (N, 2) point: top-view distance to the polyline, the polyline's z there, and whether
    the point lies beside it (its foot not past either end)."""
    p = np.asarray(polyline, dtype=np.float64)
    a, d = p[:-1, :2], np.diff(p[:, :2], axis=0)
    rel = xy[:, None, :] - a[None]  # (N, S, 2)
    t_raw = (rel * d[None]).sum(axis=2) / np.maximum((d ** 2).sum(axis=1), 1e-12)
    t = np.clip(t_raw, 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * d[None], axis=2)
    k = dist.argmin(axis=1)
    rows = np.arange(len(xy))
    tk, last = t_raw[rows, k], len(d) - 1
    beside = ~(((k == 0) & (tk < 0)) | ((k == last) & (tk > 1)))
    z = p[k, 2] + t[rows, k] * (p[k + 1, 2] - p[k, 2])
    return dist[rows, k], z, beside


def near_line(xyz: np.ndarray, polyline: np.ndarray, reach: float,
              level: float = LEVEL_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of the ground returns within `reach` (top view) of the polyline, with their
    distances and whether each lies beside it (line_frame); ground: within `level` of its z."""
    lo, hi = polyline[:, :2].min(axis=0) - reach, polyline[:, :2].max(axis=0) + reach
    index = np.flatnonzero(((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi)).all(axis=1))
    dist, z, beside = line_frame(xyz[index, :2], polyline)
    keep = (dist <= reach) & (np.abs(xyz[index, 2] - z) < level)
    return index[keep], dist[keep], beside[keep]


def sweep_rings(xyz: np.ndarray, ring: np.ndarray | None,
                polylines: Sequence[np.ndarray]) -> np.ndarray:
    """(N,) laser index per return: the ring column, else elevation clusters of the sweep's
    ground returns (ground_mask) and those near the lines, formed together as contrast_rings
    forms them: a laser's whole circle keeps its cluster whole, where the returns of one short
    stretch (a laser origin off the sensor's shifts its elevation with azimuth) would split
    it. -1: a return in neither."""
    if ring is not None:
        return np.asarray(ring).astype(np.int64)
    member = ground_mask(xyz)
    for polyline in polylines:
        member[near_line(xyz, polyline, BESIDE_M[1])[0]] = True
    ids = np.full(len(xyz), -1, dtype=np.int64)
    ids[member] = elevation_ring_ids(xyz[member])
    return ids


def group_medians(ids: np.ndarray, values: np.ndarray, min_count: int) -> np.ndarray:
    """Median of values per id, for the ids with at least min_count values."""
    if ids.size == 0:
        return np.zeros(0)
    order = np.lexsort((values, ids))
    ids, values = ids[order], values[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    counts = np.diff(np.r_[starts, ids.size])
    medians = 0.5 * (values[starts + (counts - 1) // 2] + values[starts + counts // 2])
    return medians[counts >= min_count]


def _ratio(values: np.ndarray, on: np.ndarray, side: np.ndarray) -> float | None:
    if not on.any() or not side.any():
        return None
    road = float(np.median(values[side]))
    return float(np.median(values[on])) / road if road > 0 else None


def measure_line(xyz: np.ndarray, raw: np.ndarray, encodings: Sequence[np.ndarray],
                 polyline: np.ndarray, rings: np.ndarray) -> dict[str, Any]:
    """returns, rings, contrast per encoding and ring spread of one labelled line (rings:
    sweep_rings)."""
    index, dist, beside = near_line(xyz, polyline, BESIDE_M[1])
    on = dist <= NEAR_M
    side = beside & (dist >= BESIDE_M[0])
    ids = rings[index]
    logs = np.log(np.maximum(raw[index], 1e-12))
    medians = group_medians(ids[side & (raw[index] > 0)], logs[side & (raw[index] > 0)],
                            MIN_RING_RETURNS)
    return {'returns': int(on.sum()), 'rings': int(np.unique(ids[on]).size),
            'contrasts': [_ratio(values[index], on, side) for values in encodings],
            'ring_spread': float(np.std(medians)) if medians.size >= 2 else None}


def verdict(found: bool, best: float | None, threshold: float) -> str:
    """One word from the facts (VERDICTS)."""
    if found:
        return 'found'
    if best is None:
        return 'no-candidate'
    return 'low-score' if best < threshold else 'paint-check'


def model_facts(line: np.ndarray, capture: _Capture, params: DetectorParams, scoring: Scoring,
                half: float) -> tuple[float | None, str, str]:
    """Best confidence of a candidate on the line; whether that candidate is kept by the paint
    check alone and by the evidence cut alone ('-' without one, or for the classical detector,
    which has no checks)."""
    window, (lanes, confidences) = capture.window, capture.output
    assert window is not None
    on = [i for i in np.flatnonzero(confidences >= LOW_THRESHOLD)
          if scoring.coverage(line, [window.to_output(lanes[i])], half) >= SHARE]
    if not on:
        return None, '-', '-'
    best = max(on, key=lambda i: confidences[i])
    if params.detector == 'classical':
        return float(confidences[best]), '-', '-'

    def survives(check: DetectorParams) -> bool:
        kept, _ = with_evidence([lanes[best]], confidences[best:best + 1], window, check)
        return scoring.coverage(line, [window.to_output(k) for k in kept], half) >= SHARE
    paint = survives(dataclasses.replace(params, evidence_reach_m=0.0))
    evidence = survives(dataclasses.replace(params, min_paint_contrast=0.0))
    return float(confidences[best]), 'kept' if paint else 'dropped', 'kept' if evidence else 'cut'


def published(capture: _Capture, params: DetectorParams) -> list[np.ndarray]:
    """The node's lanes (sensor frame) from the captured output: score threshold, then (FHLD)
    the evidence checks; each lane on its own, as the node treats it."""
    window, (lanes, confidences) = capture.window, capture.output
    assert window is not None
    keep = np.flatnonzero(confidences >= params.score_threshold)
    kept = [lanes[i] for i in keep]
    if params.detector != 'classical':
        kept, _ = with_evidence(kept, confidences[keep], window, params)
    return [window.to_output(lane) for lane in kept]


def diagnose_sweep(scan: Any, sweep: np.ndarray, params: DetectorParams, capture: _Capture,
                   scoring: Scoring) -> SweepDiagnosis:
    """Facts for every labelled line of one sweep (scan: a real_scans.ScanLabels) at gain 1."""
    half = params.size_px * params.resolution_m / 2
    capture.window = None
    scoring.detect_sweep(dataclasses.replace(params, score_threshold=0.0), capture,
                         cloud_points(sweep))
    window, (lanes, confidences) = capture.window, capture.output
    assert window is not None, 'the pipeline did not run the detector'
    shown = published(capture, params)
    xyz32 = np.stack([sweep['x'], sweep['y'], sweep['z']], axis=1).astype(np.float32)
    xyz = xyz32.astype(np.float64)
    raw = sweep['intensity'].astype(np.float32)  # as the node reads it
    ring = sweep['ring'] if 'ring' in (sweep.dtype.names or ()) else None
    # encoded as the node encodes this sweep: its ring field too, where the encoding uses one
    encodings = [IntensityEncoder(capture.intensity_encoding)(xyz32, raw, ring=ring)]
    if capture.intensity_encoding != CONTRAST:
        encodings.append(IntensityEncoder(CONTRAST)(xyz32, raw))
    rings = sweep_rings(xyz, ring, [line.points for line in scan.lines])
    lines = []
    for line in scan.lines:
        measured = measure_line(xyz, raw.astype(np.float64), encodings, line.points, rings)
        found = scoring.coverage(line.points, shown, half) >= SHARE
        best, paint, evidence = model_facts(line.points, capture, params, scoring, half)
        contrasts = measured['contrasts'] + [None]
        lines.append((line.points, LineFacts(
            scan.file, scan.sensor, line.id, found, measured['returns'], measured['rings'],
            contrasts[0], contrasts[1], measured['ring_spread'], best, paint, evidence,
            verdict(found, best, params.score_threshold))))
    candidates = np.flatnonzero(confidences >= LOW_THRESHOLD)
    return SweepDiagnosis(scan.file, xyz, encodings[0],
                          [window.to_output(lanes[i]) for i in candidates],
                          confidences[candidates], lines)


def _fmt(value: float | None, digits: int = 2) -> str:
    return '-' if value is None else f'{value:.{digits}f}'


def print_facts(facts: list[LineFacts], detector: str, encoding: str, file: Any = None) -> None:
    file = file or sys.stdout
    plain = encoding != CONTRAST
    print(f'detector {detector}, encoding {encoding}, gain 1: per labelled line (returns within '
          f'{NEAR_M} m; contrast on / beside {BESIDE_M[0]}-{BESIDE_M[1]} m'
          + ('; contrast* under `contrast`' if plain else '') + ')', file=file)
    print(f'{"scan":31s} {"line":19s} {"found":5s} {"ret":>5s} {"rings":>5s} {"contr":>6s}'
          + (f' {"contr*":>6s}' if plain else '')
          + f' {"spread":>6s} {"best":>5s} {"paint":>7s} {"evid":>5s}  verdict', file=file)
    for f in facts:
        print(f'{Path(f.file).stem[:31]:31s} {f.line[:19]:19s} {"yes" if f.found else "no":5s} '
              f'{f.returns:5d} {f.rings:5d} {_fmt(f.contrast):>6s}'
              + (f' {_fmt(f.contrast_plain):>6s}' if plain else '')
              + f' {_fmt(f.ring_spread):>6s} {_fmt(f.best):>5s} {f.paint:>7s} {f.evidence:>5s}'
              f'  {f.verdict}', file=file)
    counts = {name: sum(f.verdict == name for f in facts) for name in VERDICTS}
    print('verdicts: ' + ', '.join(f'{name} {n}' for name, n in counts.items()), file=file)


def _chosen(diagnoses: list[SweepDiagnosis]) -> list[tuple[SweepDiagnosis, np.ndarray,
                                                           LineFacts]]:
    """The missed lines; when none is missed, the two with the lowest best confidence."""
    every = [(d, polyline, f) for d in diagnoses for polyline, f in d.lines]
    missed = [item for item in every if item[2].verdict != 'found']
    return missed or sorted(every, key=lambda item: -1.0 if item[2].best is None
                            else item[2].best)[:2]


def _draw_line(ax: Any, sweep: SweepDiagnosis, polyline: np.ndarray, facts: LineFacts) -> Any:
    """One top-view crop: ground returns by contrast, the label, the candidates."""
    xy = polyline[:, :2]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    centre = np.array([np.interp(arc[-1] / 2, arc, xy[:, k]) for k in (0, 1)])
    lo, hi = centre - np.array(CROP_M) / 2, centre + np.array(CROP_M) / 2
    index = np.flatnonzero(((sweep.xyz[:, :2] >= lo) & (sweep.xyz[:, :2] <= hi)).all(axis=1))
    _, z, _ = line_frame(sweep.xyz[index, :2], polyline)
    index = index[np.abs(sweep.xyz[index, 2] - z) < 2 * LEVEL_M]  # the road, roughly
    shade = sweep.encoded[index]
    road = float(np.median(shade)) if shade.size else 1.0
    shade = shade / road if road > 0 else shade
    order = np.argsort(shade)  # bright returns drawn last, on top
    dots = ax.scatter(sweep.xyz[index[order], 0], sweep.xyz[index[order], 1], c=shade[order],
                      s=3, cmap='viridis', vmin=0.5, vmax=2.0, linewidths=0)
    ax.plot(xy[:, 0], xy[:, 1], color='cyan', lw=1.5, zorder=2)
    shown = [(lane, c) for lane, c in zip(sweep.candidates, sweep.confidences)
             if ((lane[:, :2] >= lo) & (lane[:, :2] <= hi)).all(axis=1).any()]
    for k, (lane, confidence) in enumerate(shown):
        ax.plot(lane[:, 0], lane[:, 1], '--', color='orangered', lw=1.2, zorder=3)
        # labels spread along x, so those of neighbouring lanes do not overlap
        inside = np.flatnonzero(((lane[:, :2] >= lo) & (lane[:, :2] <= hi)).all(axis=1))
        at = lane[inside[int((k + 1) / (len(shown) + 1) * (len(inside) - 1))]]
        ax.text(at[0], at[1] + 0.12, f'{confidence:.2f}', color='orangered', fontsize=8,
                zorder=4, bbox={'facecolor': 'white', 'alpha': 0.7, 'pad': 1, 'lw': 0})
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect('equal')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_title(f'{Path(facts.file).stem} {facts.line}: {facts.verdict}\n{facts.returns} '
                 f'returns from {facts.rings} rings, contrast {_fmt(facts.contrast)}, ring '
                 f'spread {_fmt(facts.ring_spread)}, best candidate {_fmt(facts.best)}',
                 fontsize=9)
    return dots


def draw_figure(diagnoses: list[SweepDiagnosis], path: Path) -> int:
    """One PNG with a crop per chosen line (_chosen); returns how many lines it shows."""
    chosen = _chosen(diagnoses)
    if not chosen:
        return 0
    fig = Figure(figsize=(10, 4.6 * len(chosen)), layout='constrained')
    axes = fig.subplots(len(chosen), 1, squeeze=False)[:, 0]
    for ax, (sweep, polyline, facts) in zip(axes, chosen):
        dots = _draw_line(ax, sweep, polyline, facts)
    fig.colorbar(dots, ax=list(axes), shrink=0.8,
                 label='encoded intensity / median of the road in the crop')
    fig.savefig(path, dpi=90, bbox_inches='tight')
    return len(chosen)


def run(args: argparse.Namespace, params: DetectorParams, present: Sequence[Any],
        sweeps: dict[str, np.ndarray], scoring: Scoring) -> int:
    """`fhld realscans --explain [--explain-figure PNG] [--json]`; present: the labelled
    real_scans.ScanLabels whose sweeps (read_sweep, by file name) are in `sweeps`."""
    capture = capture_detector(params)
    diagnoses = [diagnose_sweep(scan, sweeps[scan.file], params, capture, scoring)
                 for scan in present if scan.lines]
    facts = [f for d in diagnoses for _, f in d.lines]
    print_facts(facts, params.detector, capture.intensity_encoding)
    if args.explain_figure is not None:
        shown = draw_figure(diagnoses, args.explain_figure)
        print(f'wrote {args.explain_figure} ({shown} lines)')
    if args.json:
        print(json.dumps({'detector': params.detector, 'encoding': capture.intensity_encoding,
                          'score_threshold': params.score_threshold,
                          'low_threshold': LOW_THRESHOLD,
                          'lines': [dataclasses.asdict(f) for f in facts]}))
    return 0
