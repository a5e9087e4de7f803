"""`fhld realscans [DIR]`: the detector on real single LiDAR sweeps, scored against hand labels.

Each sweep goes through the node's own path: one PointCloud2 (create_cloud, fields x y z
intensity float32) into a LanePipeline without odometry, so the window is that sweep alone in
the cloud frame. The intensity is multiplied by a gain first (x1 = the sensor's own units) to
see whether the lanes depend on the sensor's brightness scale. Labels and how they were made:
docs/real_scans.md.

Sweep layouts, by file name (read_sweep): `*.fp16x5.bin` float16 x y z intensity dt (nuScenes
sweeps accumulated in the newest one's LIDAR_TOP frame), `*.pcd.bin` float32 x y z intensity
ring (one nuScenes LIDAR_TOP sweep), any other `.bin` float32 x y z intensity (KITTI, sensor
frame). nuScenes' LIDAR_TOP frame has x right, y forward: it is turned into the sensor frame
(x forward, y left, z up) as x = y_nu, y = -x_nu.

Scores, in top view, inside the window (|x|, |y| < 12.8 m):
* a labelled line is FOUND when >= 50 % of its points (resampled every 0.2 m) lie within
  0.3 m of a published lane;
* a published lane is FALSE when < 50 % of its points lie within 0.3 m of a labelled line
  (on the no-paint scan every lane is false).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fhld_ros.bagio import BagWriter
from fhld_ros.data.bag_source import LANES_GT, MARKER_ARRAY, POINTS, TOPIC_TYPES
from fhld_ros.data.samples import scale_intensity
from fhld_ros.detectors import make_detector
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation import real_scan_diagnosis
from fhld_ros.importing.kitti import read_bin
from fhld_ros.importing.pcd import XYZI_DTYPE, cloud_points
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import LaneDetector, LanePipeline
from msg_adapters.family import rosbags_family
from msg_adapters.lanes import lanes_to_marker_array_cdr
from msg_adapters.pointcloud2 import create_cloud

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DIR = REPO.parent / 'shared' / 'real_scans'
LABELS = REPO / 'docs' / 'real_scan_labels.json'
STEP_M = 0.2  # resampling step of labels and lanes
MATCH_M = 0.3  # top-view distance within which a point counts as on the other line
SHARE = 0.5  # share of a line's points that must match
GAINS = (1.0, 0.5, 2.0)
# (name suffix, scalar type, fifth column or None, nuScenes LIDAR_TOP frame): the first match
# wins, so '.bin' (KITTI) is last
SWEEP_LAYOUTS: tuple[tuple[str, str, str | None, bool], ...] = (
    ('.fp16x5.bin', '<f2', 'dt', True),
    ('.pcd.bin', '<f4', 'ring', True),
    ('.bin', '<f4', None, False),
)


def read_sweep(path: str | Path) -> np.ndarray:
    """A sweep as a structured float32 array in the sensor frame (x forward, y left, z up).

    Fields x, y, z, intensity, then the layout's fifth column where it has one: `ring` (laser
    index, kept for a per-ring intensity normalisation) or `dt` (seconds before the newest of
    the accumulated sweeps). The layout comes from the file name (SWEEP_LAYOUTS); KITTI files
    go through importing.kitti.read_bin. ConfigError when the size does not fit the layout.
    """
    path = Path(path)
    scalar, extra, lidar_top = next(
        (layout[1:] for layout in SWEEP_LAYOUTS if path.name.endswith(layout[0])),
        ('<f4', None, False))
    if extra is None:
        return read_bin(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f'cannot read {path}: {exc.strerror or exc}') from None
    width = 5 * np.dtype(scalar).itemsize
    if len(raw) % width:
        raise ConfigError(f'{path}: {len(raw)} bytes is not a multiple of {width} ({scalar} x, '
                          f'y, z, intensity, {extra} per point): truncated or another layout')
    columns = np.frombuffer(raw, dtype=scalar).reshape(-1, 5).astype(np.float32)
    out = np.empty(len(columns), dtype=np.dtype(XYZI_DTYPE.descr + [(extra, '<f4')]))
    out['x'], out['y'] = (columns[:, 1], -columns[:, 0]) if lidar_top else columns[:, :2].T
    out['z'], out['intensity'], out[extra] = columns[:, 2:].T
    return out


@dataclass(frozen=True)
class LabelledLine:
    id: str
    kind: str  # 'solid' or 'dashed'
    points: np.ndarray  # (K, 3) sensor frame


@dataclass(frozen=True)
class ScanLabels:
    file: str
    sensor: str
    lines: tuple[LabelledLine, ...]
    notes: str = ''
    format: str = ''  # how a non-KITTI file was read and turned into the sensor frame


@dataclass
class ScanScore:
    """One sweep at one gain: per-line coverage by lanes and per-lane coverage by labels."""

    file: str
    sensor: str
    gain: float
    line_cover: dict[str, float]  # labelled line id -> share of its points near a lane
    lane_cover: list[float]  # per published lane: share of its points near a labelled line
    confidences: list[float] = field(default_factory=list)
    lanes: list[np.ndarray] = field(default_factory=list)  # (K, 3) published, cloud frame

    @property
    def found(self) -> int:
        return sum(c >= SHARE for c in self.line_cover.values())

    @property
    def false(self) -> int:
        return sum(c < SHARE for c in self.lane_cover)

    def summary(self) -> dict[str, Any]:
        return {'file': self.file, 'sensor': self.sensor, 'gain': self.gain,
                'labelled': len(self.line_cover), 'found': self.found,
                'published': len(self.lane_cover), 'false': self.false,
                'line_cover': {k: round(v, 3) for k, v in self.line_cover.items()},
                'lane_cover': [round(c, 3) for c in self.lane_cover],
                'confidences': [round(c, 3) for c in self.confidences]}


def load_labels(path: Path = LABELS) -> list[ScanLabels]:
    """The label file, checked: ValueError names the first problem."""
    document = json.loads(Path(path).read_text())
    scans = []
    for scan in document['scans']:
        lines = []
        for line in scan['lines']:
            points = np.asarray(line['points'], dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
                raise ValueError(f"{scan['file']} line {line['id']}: points must be (K >= 2, 3)")
            if not np.isfinite(points).all():
                raise ValueError(f"{scan['file']} line {line['id']}: non-finite point")
            if line['kind'] not in ('solid', 'dashed'):
                raise ValueError(f"{scan['file']} line {line['id']}: kind {line['kind']!r}")
            lines.append(LabelledLine(str(line['id']), line['kind'], points))
        ids = [line.id for line in lines]
        if len(set(ids)) != len(ids):
            raise ValueError(f"{scan['file']}: duplicate line ids")
        scans.append(ScanLabels(scan['file'], scan['sensor'], tuple(lines), scan.get('notes', ''),
                                scan.get('format', '')))
    return scans


def sweep_cloud(points: np.ndarray, gain: float, stamp_ns: int = 0,
                frame_id: str = 'lidar') -> Any:
    """A rosbags PointCloud2 of the sweep (importing.pcd.cloud_points), intensity times gain."""
    family = rosbags_family()
    return create_cloud(family.cls('sensor_msgs/msg/PointCloud2'),
                        family.header(stamp_ns, frame_id), scale_intensity(points, gain))


def write_labelled_bags(directory: Path, out: Path, names: list[str],
                        labels_path: Path = LABELS) -> list[Path]:
    """One labelled bag per named sweep (data.bags of a training YAML): its cloud on /points
    and its labelled lines on /lanes_gt, both in the sensor frame at one stamp, no /odom (so
    the sweep is a window of its own, as in the node without odometry). Names are label-file
    names; a name not labelled is a ConfigError. Existing bags are refused (BagWriter)."""
    scans = {scan.file: scan for scan in load_labels(labels_path)}
    unknown = sorted(set(names) - set(scans))
    if unknown:
        raise ConfigError(f'not in {labels_path}: {", ".join(unknown)} '
                          f'(labelled: {", ".join(sorted(scans))})')
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in names:
        scan, stamp = scans[name], 1_700_000_000 * 10**9
        path = out / Path(name).name.split('.')[0]
        lines = [line.points for line in scan.lines]
        with BagWriter(path) as bag:
            bag.write(POINTS, TOPIC_TYPES[POINTS], stamp,
                      sweep_cloud(cloud_points(read_sweep(directory / scan.file)), 1.0, stamp))
            bag.write(LANES_GT, MARKER_ARRAY, stamp, lanes_to_marker_array_cdr(
                stamp, 'lidar', lines, [1.0] * len(lines), list(range(1, len(lines) + 1))))
        written.append(path)
    return written


def detect_sweep(params: DetectorParams, detector: LaneDetector, points: np.ndarray,
                 gain: float = 1.0) -> tuple[list[np.ndarray], np.ndarray]:
    """Lanes ((K, 3) cloud frame) and confidences the pipeline publishes for one sweep.

    A fresh pipeline per sweep, as `fhld replay` runs a bag without odometry: nothing waits
    for odometry, the window is this sweep alone in the cloud frame.
    """
    pipeline = LanePipeline(params, detector, expect_odometry=False)
    pipeline.add_cloud(sweep_cloud(points, gain))
    out = pipeline.detect()
    if out is None:
        raise RuntimeError('the pipeline produced no detection for the sweep')
    return out.lanes, out.confidences


def resample_xy(polyline: np.ndarray, step: float = STEP_M,
                half: float | None = None) -> np.ndarray:
    """(M, 2) points every `step` metres of top-view arc length; inside |x|, |y| <= half."""
    xy = np.asarray(polyline, dtype=np.float64)[:, :2]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    if arc[-1] <= 0:
        samples = xy[:1]
    else:
        s = np.append(np.arange(0.0, arc[-1], step), arc[-1])
        samples = np.stack([np.interp(s, arc, xy[:, 0]), np.interp(s, arc, xy[:, 1])], axis=1)
    if half is not None:
        samples = samples[(np.abs(samples) <= half).all(axis=1)]
    return samples


def distance_to_polylines(points: np.ndarray, polylines: list[np.ndarray]) -> np.ndarray:
    """Top-view distance of each (N, 2) point to the nearest segment of any polyline."""
    segments = [np.stack([p[:-1, :2], p[1:, :2]], axis=1) for p in polylines if len(p) >= 2]
    singles = [p[:, :2] for p in polylines if len(p) == 1]
    if not segments and not singles:
        return np.full(len(points), np.inf)
    best = np.full(len(points), np.inf)
    if segments:
        seg = np.concatenate(segments)  # (S, 2, 2)
        a, d = seg[:, 0], seg[:, 1] - seg[:, 0]
        length2 = np.maximum((d ** 2).sum(axis=1), 1e-12)
        rel = points[:, None, :] - a[None]  # (N, S, 2)
        t = np.clip((rel * d[None]).sum(axis=2) / length2, 0.0, 1.0)
        best = np.linalg.norm(rel - t[..., None] * d[None], axis=2).min(axis=1)
    for single in singles:
        best = np.minimum(best, np.linalg.norm(points[:, None] - single[None], axis=2).min(1))
    return best


def coverage(line: np.ndarray, others: list[np.ndarray], half: float) -> float:
    """Share of `line`'s resampled in-window points within MATCH_M of any of `others`."""
    samples = resample_xy(line, half=half)
    if len(samples) == 0:
        return 0.0
    return float((distance_to_polylines(samples, others) <= MATCH_M).mean())


def score_scan(labels: ScanLabels, lanes: list[np.ndarray], gain: float = 1.0,
               half: float = 12.8, confidences: Any = ()) -> ScanScore:
    """Found / false bookkeeping of one sweep's published lanes against its labels."""
    labelled = [line.points for line in labels.lines]
    lanes = [np.asarray(lane, dtype=np.float64) for lane in lanes]
    return ScanScore(
        labels.file, labels.sensor, gain,
        line_cover={line.id: coverage(line.points, lanes, half) for line in labels.lines},
        lane_cover=[coverage(lane, labelled, half) for lane in lanes],
        confidences=[float(c) for c in confidences], lanes=lanes)


def present_sweeps(directory: Path, labels_path: Path = LABELS
                   ) -> tuple[list[ScanLabels], dict[str, np.ndarray]]:
    """The labelled scans found in `directory` and their sweeps (read_sweep), by file."""
    try:
        all_labels = load_labels(labels_path)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f'cannot read labels {labels_path}: {exc}') from exc
    present = [scan for scan in all_labels if (directory / scan.file).is_file()]
    if not present:
        raise ConfigError(f'{directory} holds none of the labelled scans '
                          f'({", ".join(scan.file for scan in all_labels)})')
    return present, {scan.file: read_sweep(directory / scan.file)  # ConfigError if bad
                     for scan in present}


def evaluate(directory: Path, params: DetectorParams, gains: tuple[float, ...] = GAINS,
             labels_path: Path = LABELS) -> list[ScanScore]:
    """Every labelled scan found in `directory` at every gain (one detector load)."""
    present, read = present_sweeps(directory, labels_path)
    sweeps = {name: cloud_points(sweep) for name, sweep in read.items()}
    detector = make_detector(params)
    half = params.size_px * params.resolution_m / 2
    scores = []
    for gain in gains:
        for scan in present:
            lanes, confidences = detect_sweep(params, detector, sweeps[scan.file], gain)
            scores.append(score_scan(scan, lanes, gain, half, confidences))
    return scores


def totals(scores: list[ScanScore]) -> dict[str, dict[str, dict[str, int]]]:
    """{gain: {'all' | sensor: {labelled, found, published, false}}} summed over scans."""
    out: dict[str, dict[str, dict[str, int]]] = {}
    for score in scores:
        per_gain = out.setdefault(f'{score.gain:g}', {})
        for key in ('all', score.sensor):
            row = per_gain.setdefault(key, dict.fromkeys(
                ('labelled', 'found', 'published', 'false'), 0))
            row['labelled'] += len(score.line_cover)
            row['found'] += score.found
            row['published'] += len(score.lane_cover)
            row['false'] += score.false
    return out


def print_table(scores: list[ScanScore], detector: str, file: Any = None) -> None:
    file = file or sys.stdout
    print(f'detector {detector}: lines found / labelled, false / published lanes', file=file)
    print(f'{"scan":34s} {"gain":>5s} {"found":>7s} {"false":>7s}  missed lines', file=file)
    for score in scores:
        missed = [k for k, v in score.line_cover.items() if v < SHARE]
        print(f'{Path(score.file).stem:34s} {score.gain:5g} '
              f'{score.found:>3d}/{len(score.line_cover):<3d} '
              f'{score.false:>3d}/{len(score.lane_cover):<3d}  {" ".join(missed)}', file=file)
        if not score.line_cover:  # no paint: every lane is false, say where they are
            for lane, conf in zip(score.lanes, score.confidences):
                start, end = lane[0, :2], lane[-1, :2]
                print(f'    lane conf {conf:.2f} from ({start[0]:.1f}, {start[1]:.1f}) to '
                      f'({end[0]:.1f}, {end[1]:.1f}) m', file=file)
    for gain, rows in totals(scores).items():
        for key, row in rows.items():
            print(f'total gain {gain:>4s} {key:40s} found {row["found"]}/{row["labelled"]}, '
                  f'false {row["false"]}/{row["published"]}', file=file)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    default = DEFAULT_DIR if DEFAULT_DIR.is_dir() else None
    parser.add_argument('directory', nargs='?' if default else None, type=Path, default=default,
                        metavar='DIR', help='folder with the real .bin sweeps'
                        + (f' (default {default})' if default else ''))
    parser.add_argument('--gains', type=float, nargs='+', default=list(GAINS),
                        help='intensity gains (default 1 0.5 2; 1 = the sensor\'s own units)')
    parser.add_argument('--detector', choices=['fhld', 'classical'], default='fhld')
    parser.add_argument('--checkpoint', help='FHLD weights (default: the shipped checkpoint)')
    parser.add_argument('--labels', type=Path, default=LABELS, help='label file (JSON)')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')
    parser.add_argument('--write-bags', type=Path, metavar='OUT',
                        help='instead of scoring: write OUT/<sweep>/, a labelled training bag '
                        'per sweep named by --scans (data.bags of a training YAML)')
    parser.add_argument('--scans', nargs='+', default=[], metavar='FILE',
                        help='label-file names of the sweeps for --write-bags')
    parser.add_argument('--explain', action='store_true', help='instead of scoring: per '
                        'labelled line at gain 1, why it is found or missed (real_scan_diagnosis)')
    parser.add_argument('--explain-figure', type=Path, metavar='PNG',
                        help='with --explain: top views of the missed lines, one PNG')


def run(args: argparse.Namespace) -> int:
    if not args.directory.is_dir():
        raise ConfigError(f'{args.directory} is not a directory')
    if any(not gain > 0 for gain in args.gains):
        raise ConfigError('gains must be > 0')
    if args.write_bags is not None:
        if not args.scans:
            raise ConfigError('--write-bags needs --scans')
        for path in write_labelled_bags(args.directory, args.write_bags, args.scans,
                                        args.labels):
            print(f'wrote {path}')
        return 0
    params = dataclasses.replace(DetectorParams(), detector=args.detector,
                                 checkpoint=args.checkpoint or '')
    if args.explain or args.explain_figure is not None:
        return real_scan_diagnosis.run(args, params, *present_sweeps(args.directory, args.labels),
                                       real_scan_diagnosis.Scoring(coverage, detect_sweep))
    scores = evaluate(args.directory, params, tuple(args.gains), args.labels)
    print_table(scores, args.detector)
    if args.json:
        print(json.dumps({'detector': args.detector, 'gains': list(args.gains),
                          'scans': [score.summary() for score in scores],
                          'totals': totals(scores)}))
    return 0
