"""`fhld autolabel-eval`: `fhld autolabel` on held-out simulated drives, scored against the
simulator's 3D ground truth (docs/annotation.md, "Accuracy").

Each drive goes the user's way: `fhld simulate --camera --labels2d` writes the bag and the 2D
labels, the labels are optionally perturbed (--perturb-px P: every label point moved by an
independent uniform offset in [-P, P] px in u and in v), `fhld autolabel` lifts them and
`fhld eval` scores its /lanes twice: against /camera/lanes_gt, the 3D GT of exactly what the
labels show (the lift's accuracy), and against /lanes_gt, every GT line in the output window
(also counting what the camera never saw: hidden by vehicles, outside its field of view).
Seeds AUTOLABEL_SEED_BASE.. are held out from training and from the detector's test set; the
sensor presets take turns.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fhld_ros.annotation.labels2d import read_label_dir, write_labels
from fhld_ros.cli import main as fhld
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation.evaluate import evaluate_bags, summary
from fhld_ros.sim.lidar import SENSORS
from fhld_ros.training.cache import TEST_SEED_BASE

AUTOLABEL_SEED_BASE = TEST_SEED_BASE + 500_000
VISIBLE_GT, ALL_GT = '/camera/lanes_gt', '/lanes_gt'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--drives', type=int, default=8, help='held-out drives (default 8)')
    parser.add_argument('--sweeps', type=int, default=30, help='sweeps per drive (default 30)')
    parser.add_argument('--perturb-px', type=float, default=0.0, metavar='P',
                        help='move every 2D label point by up to P px in u and v (default 0)')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def perturb_labels(src: Path, dst: Path, px: float, seed: int) -> None:
    """Copy the label files of src into dst with every point moved by U(-px, px) in u and v."""
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    for stamp, labels in sorted(read_label_dir(src).items()):
        for lane in labels.lanes:
            lane.uv = lane.uv + rng.uniform(-px, px, lane.uv.shape)
        write_labels(dst / f'{stamp}.json', labels)


def run_drive(work: Path, seed: int, sensor: str, sweeps: int, perturb_px: float
              ) -> tuple[list, list, float]:
    """Frames scored against the visible and the full GT, and autolabel's seconds."""
    bag, labels, lanes = work / 'drive', work / 'labels2d', work / 'autolabel'
    quiet = ['--quiet']
    if fhld(['simulate', str(bag), '--seed', str(seed), '--sweeps', str(sweeps), '--sensor',
             sensor, '--camera', '--labels2d', str(labels), *quiet]) != 0:
        raise ConfigError(f'fhld simulate failed for seed {seed}')
    if perturb_px > 0:
        perturb_labels(labels, work / 'perturbed', perturb_px, seed)
        labels = work / 'perturbed'
    start = time.perf_counter()
    if fhld(['autolabel', str(bag), str(lanes), '--labels2d', str(labels), *quiet]) != 0:
        raise ConfigError(f'fhld autolabel failed for seed {seed}')
    seconds = time.perf_counter() - start
    args = {topic: argparse.Namespace(pred_bag=str(lanes), gt_bag=str(bag), pred_topic='/lanes',
                                      gt_topic=topic, once_official=False, score_thresh=0.1)
            for topic in (VISIBLE_GT, ALL_GT)}
    return evaluate_bags(args[VISIBLE_GT]), evaluate_bags(args[ALL_GT]), seconds


def run(args: argparse.Namespace) -> int:
    if args.drives < 1 or args.sweeps < 1:
        raise ConfigError('--drives and --sweeps must be >= 1')
    if not 0 <= args.perturb_px <= 50:
        raise ConfigError(f'--perturb-px must be within 0..50, got {args.perturb_px:g}')
    sensors = list(SENSORS)
    visible, full, seconds = [], [], []
    with tempfile.TemporaryDirectory(prefix='fhld-autolabel-eval-') as tmp:
        for k in range(args.drives):
            seed, sensor = AUTOLABEL_SEED_BASE + k, sensors[k % len(sensors)]
            work = Path(tmp) / f'drive_{k}'
            work.mkdir()
            v, f, s = run_drive(work, seed, sensor, args.sweeps, args.perturb_px)
            visible += v
            full += f
            seconds.append(s)
            one = summary(v)['point']
            print(f'drive {k} (seed {seed}, {sensor}): {len(v)} images, F1@10 '
                  f'{one["F1@10"]:.1f}, F1@30 {one["F1@30"]:.1f}, autolabel {s:.1f} s',
                  file=sys.stderr)
    result = {'drives': args.drives, 'sweeps': args.sweeps, 'perturb_px': args.perturb_px,
              'visible_gt': summary(visible), 'all_gt': summary(full),
              'autolabel_seconds': {'median': float(np.median(seconds)),
                                    'max': float(np.max(seconds))}}
    for name, title in (('visible_gt', 'GT the labels show'), ('all_gt', 'all GT in window')):
        p, o = result[name]['point'], result[name]['once']
        print(f'{title:<20} F1@10 {p["F1@10"]:6.2f}  F1@30 {p["F1@30"]:6.2f}  '
              f'(P@10 {p["P@10"]:.2f} R@10 {p["R@10"]:.2f})  ONCE F1 {o["F1"]:6.2f}  '
              f'CD {o["CD"]:.3f} m')
    print(f'autolabel per {args.sweeps}-sweep drive: median '
          f'{result["autolabel_seconds"]["median"]:.1f} s, max '
          f'{result["autolabel_seconds"]["max"]:.1f} s')
    if args.json:
        print(json.dumps(result))
    return 0
