"""`fhld testset`: every detector on the same held-out simulated windows, one table.

The test set is fixed: seeds TEST_SEED_BASE .. +55 (unseen by training, which uses seeds from
0), 4 windows each = 224 windows of 25.6 m, and with the cache's scenario rule these 56 seeds
cover every sensor preset x topology pair. Each window goes through the node's own path
(PointCloud2 -> RollingBevGrid.read_cloud -> insert); the detectors see the identical
BevWindow, with the FHLD checkpoint's intensity encoding when an FHLD row is asked for:

* `classical`   rule-based baseline on the window's accumulated points
* `fhld`        the FHLD model's final output (local branch points, heights refined from the
                measured surface: model/heights.py)
* `fhld-model-z` the same lanes with the local branch's own heights (no refinement)
* `fhld-global` the same model's global curves alone (the paper's "without local branch" row)

The three FHLD rows are one eager-torch detection per window (detectors.fhld_variants); the
node serves the same weights through ONNX Runtime/TorchScript, equal to float rounding.

Scores: the FHLD point metric and the ONCE-3DLanes lane metric, counts summed over windows;
the point metric's F1 also per sensor preset and per topology setting; lanes published and
false lanes (published, not matched by the ONCE metric) per window.

`--validation` takes the seeds from VALIDATION_SEED_BASE instead (unseen by training and by
the test set): what design choices and checkpoints are chosen on, so the test set stays a
measurement.

`--condition` makes the same seeds' windows under one real-sensor variation (CONDITIONS,
docs/testset_conditions.md): intensity gain or units, worn paint, no markings, single sweeps
without odometry. The report records it and the median paint / asphalt contrast of the
windows' newest sweeps (data/samples.py:paint_contrast).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fhld_ros.data.cache import (
    TEST_SEED_BASE,
    CacheSettings,
    scenario_for_seed,
    single_sweep_windows,
)
from fhld_ros.data.samples import training_samples
from fhld_ros.detectors import (
    FHLD_VARIANTS,
    classical_detector,
    fhld_variants,
    load_fhld_model,
)
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation import metrics
from fhld_ros.intensity import ABSOLUTE
from fhld_ros.parameters import DetectorParams
from fhld_ros.rolling_grid import BevWindow
from fhld_ros.sim.lidar import SENSORS
from fhld_ros.sim.simulator import Simulator

DETECTORS = ('classical', *FHLD_VARIANTS)
SEEDS = 56
VALIDATION_SEED_BASE = 2_000_000
WINDOWS_PER_SEED = 4
WORN_PAINT_CONTRAST = 2.5  # worn paint: reflectance at most 2.5 x the asphalt, no beads


@dataclass(frozen=True)
class Condition:
    """How a condition makes its windows: simulator options on top of the seed's scenario,
    a gain on every cloud's intensity field, or single sweeps without odometry."""

    help: str
    sim: dict = field(default_factory=dict)
    gain: float = 1.0
    single_sweep: bool = False


CONDITIONS: dict[str, Condition] = {
    **{f'gain-{g:g}': Condition(f'intensity field x{g:g} (integer fields saturate)', gain=g)
       for g in (0.25, 0.5, 2.0, 4.0)},
    'units-float': Condition('intensity as float 0-1', {'intensity': 'float'}),
    'units-u8': Condition('intensity as 0-255 (float field)', {'intensity': 'u8'}),
    'units-uint16': Condition('uint16 calibrated reflectivity', {'intensity': 'reflectivity'}),
    'worn-paint': Condition(f'paint without beads, <= {WORN_PAINT_CONTRAST:g} x the asphalt',
                            {'paint_contrast': WORN_PAINT_CONTRAST}),
    'no-markings': Condition('the same roads without paint: no GT lines', {'markings': False}),
    'single-sweep': Condition('one sweep per window, no odometry: the cloud frame',
                              single_sweep=True),
}

_worker: dict = {}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--detectors', nargs='+', choices=DETECTORS, default=list(DETECTORS))
    parser.add_argument('--seeds', type=int, default=SEEDS, help='test seeds (default 56)')
    parser.add_argument('--windows-per-seed', type=int, default=WINDOWS_PER_SEED)
    parser.add_argument('--validation', action='store_true',
                        help=f'validation seeds from {VALIDATION_SEED_BASE:,} instead of the '
                             'test set\'s: for choosing settings and checkpoints')
    parser.add_argument('--checkpoint', type=Path, help='FHLD weights (default: shipped)')
    parser.add_argument('--score-threshold', type=float,
                        default=DetectorParams().score_threshold, help='(default: the node\'s)')
    parser.add_argument('--sensor', choices=sorted(SENSORS),
                        help='every seed with this sensor preset instead of its own (e.g. '
                             'forward70, the forward-only scanner); topologies stay the same')
    parser.add_argument('--condition', choices=list(CONDITIONS),
                        help='the same windows under a real-sensor variation: ' + '; '.join(
                            f'{name}: {c.help}' for name, c in CONDITIONS.items()))
    parser.add_argument('--workers', type=int, default=2, help='parallel processes')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def _init(detectors: list[str], params: DetectorParams) -> None:
    """Worker set-up: the detectors once per process (the eager model, one torch thread)."""
    _worker['detectors'] = detectors
    if 'classical' in detectors:
        _worker['classical'] = classical_detector()
    if set(FHLD_VARIANTS) & set(detectors):
        _worker['fhld'] = fhld_variants(params, eager=True)


def _detect(window: BevWindow) -> dict[str, list[np.ndarray]]:
    found: dict[str, list[np.ndarray]] = {}
    if 'classical' in _worker:
        found['classical'] = _worker['classical'](window)[0]
    if 'fhld' in _worker:
        found.update(_worker['fhld'](window))
    return {name: found[name] for name in _worker['detectors']}


def evaluate_seed(seed: int, windows: int, sensor: str | None = None,
                  condition: str | None = None) -> dict:
    """Counts per detector for one test seed (runs in a worker process)."""
    settings = CacheSettings(windows_per_seed=windows)
    scenario = scenario_for_seed(seed, settings)
    if sensor is not None:
        scenario['sensor'] = sensor
    cond = CONDITIONS[condition] if condition else Condition('')
    sim = Simulator(seed, sweeps=settings.sweeps_per_seed, **scenario, **cond.sim)
    # single sweeps end where the accumulated windows end: the same instants of the drive
    how = single_sweep_windows(settings) if cond.single_sweep else {}
    point = {name: metrics.PointCounts() for name in _worker['detectors']}
    once = {name: metrics.LaneCounts() for name in _worker['detectors']}
    count, contrast = 0, []
    encoding = getattr(_worker.get('fhld'), 'intensity_encoding', ABSOLUTE)
    for sample in training_samples(sim, windows, keep_window=True, intensity_gain=cond.gain,
                                   intensity_encoding=encoding, **how):
        contrast.append(sample.meta['paint_contrast'])
        half = sample.window.spec.length_m / 2
        for name, lanes in _detect(sample.window).items():
            lanes = metrics.clip_lanes_to_square(lanes, half)
            point[name] += metrics.point_counts(lanes, sample.lanes)
            once[name] += metrics.once_counts(lanes, sample.lanes, half)
        count += 1
    return {'seed': seed, 'windows': count, 'scenario': scenario, 'point': point,
            'once': once, 'paint_contrast': contrast}


def run(args: argparse.Namespace) -> int:
    if args.seeds < 1 or args.windows_per_seed < 1 or args.workers < 1:
        raise ConfigError('--seeds, --windows-per-seed and --workers must be >= 1')
    params = DetectorParams(checkpoint=str(args.checkpoint or ''), model_threads=1,
                            score_threshold=args.score_threshold)
    if set(FHLD_VARIANTS) & set(args.detectors):
        load_fhld_model(params)  # an unusable checkpoint fails here, not in every worker
    base = VALIDATION_SEED_BASE if args.validation else TEST_SEED_BASE
    seeds = list(range(base, base + args.seeds))
    init = (args.detectors, params)
    start = time.monotonic()
    with ProcessPoolExecutor(args.workers, mp_context=get_context('spawn'), initializer=_init,
                             initargs=init) as pool:
        futures = [pool.submit(evaluate_seed, seed, args.windows_per_seed, args.sensor,
                               args.condition) for seed in seeds]
        results = [f.result() for f in tqdm(futures, desc='test set', unit='seed',
                                            file=sys.stderr)]
    report = summarise(results, args.detectors, args.condition)
    report['split'] = 'validation' if args.validation else 'test'
    report['seconds'] = round(time.monotonic() - start, 1)
    print_table(report)
    if args.json:
        print(json.dumps(report))
    return 0


def summarise(results: list[dict], detectors: list[str], condition: str | None = None) -> dict:
    windows = sum(r['windows'] for r in results)
    contrast = [c for r in results for c in r.get('paint_contrast', ()) if np.isfinite(c)]
    report: dict = {'condition': condition or 'none', 'windows': windows,
                    'seeds': len(results),
                    'sensors': sorted({r['scenario']['sensor'] for r in results}),
                    'topologies': sorted({str(r['scenario']['topology']) for r in results}),
                    'paint_contrast': round(float(np.median(contrast)), 2) if contrast else None,
                    'detectors': {}}
    for name in detectors:
        point = sum((r['point'][name] for r in results), metrics.PointCounts())
        once = sum((r['once'][name] for r in results), metrics.LaneCounts())
        report['detectors'][name] = {
            'point': {k: round(v, 2) for k, v in point.scores().items()},
            'once': {k: round(v, 4 if k == 'CD' else 2) for k, v in once.scores().items()},
            'lanes_per_window': round(once.n_pred / max(windows, 1), 3),
            'false_lanes_per_window': round((once.n_pred - once.tp) / max(windows, 1), 3)}
    for key in ('sensor', 'topology'):
        report[f'by_{key}'] = _point_f1_by(results, detectors, key)
    return report


def _point_f1_by(results: list[dict], detectors: list[str], key: str) -> dict:
    """{scenario value: {'windows': n, detector: {'F1@10': .., 'F1@30': ..}}}."""
    groups: dict[str, list[dict]] = {}
    for r in results:
        groups.setdefault(str(r['scenario'][key]), []).append(r)
    table = {}
    for value, group in sorted(groups.items()):
        row: dict = {'windows': sum(r['windows'] for r in group)}
        for name in detectors:
            scores = sum((r['point'][name] for r in group), metrics.PointCounts()).scores()
            row[name] = {k: round(v, 2) for k, v in scores.items() if k.startswith('F1')}
        table[value] = row
    return table


def print_table(report: dict) -> None:
    condition = report.get('condition', 'none')
    contrast = report.get('paint_contrast')
    split = 'validation set' if report.get('split') == 'validation' else 'held-out test set'
    print(f'{split}: {report["windows"]} windows from {report["seeds"]} seeds, '
          f'{len(report["sensors"])} sensors, {len(report["topologies"])} topology settings; '
          f'condition: {condition}'
          + (f' ({CONDITIONS[condition].help})' if condition in CONDITIONS else '')
          + (f'; paint / asphalt contrast {contrast:.2f}' if contrast is not None else ''))
    header = f'{"detector":<13} {"P@10":>6} {"R@10":>6} {"F1@10":>6} {"P@30":>6} {"R@30":>6} ' \
             f'{"F1@30":>6} | {"ONCE P":>6} {"R":>6} {"F1":>6} {"CD m":>6} | ' \
             f'{"lanes/win":>9} {"false/win":>9}'
    print(header)
    for name, scores in report['detectors'].items():
        p, o = scores['point'], scores['once']
        print(f'{name:<13} {p["P@10"]:6.2f} {p["R@10"]:6.2f} {p["F1@10"]:6.2f} '
              f'{p["P@30"]:6.2f} {p["R@30"]:6.2f} {p["F1@30"]:6.2f} | {o["P"]:6.2f} '
              f'{o["R"]:6.2f} {o["F1"]:6.2f} {o["CD"]:6.3f} | '
              f'{scores["lanes_per_window"]:9.3f} {scores["false_lanes_per_window"]:9.3f}')
    names = list(report['detectors'])
    for key in ('sensor', 'topology'):
        print(f'\npoint F1@10 / F1@30 by {key}')
        print(f'{key:<14} {"windows":>7} ' + ' '.join(f'{n:>15}' for n in names))
        for value, row in report[f'by_{key}'].items():
            cells = ' '.join(f'{row[n]["F1@10"]:7.2f} {row[n]["F1@30"]:7.2f}' for n in names)
            print(f'{value:<14} {row["windows"]:>7} {cells}')
