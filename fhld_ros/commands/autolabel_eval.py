"""`fhld autolabel-eval`: `fhld autolabel` on held-out simulated drives, scored against the
simulator's 3D ground truth (docs/annotation.md, "Accuracy").

Each drive goes the user's way: `fhld simulate --camera --labels2d` writes the bag and the 2D
labels, the labels are optionally perturbed (--perturb-px P: every label point moved by an
independent uniform offset in [-P, P] px in u and in v), `fhld autolabel` lifts them and
`fhld eval` scores its /lanes twice: against /camera/lanes_gt, the 3D GT of exactly what the
labels show (the lift's accuracy), and against /lanes_gt, every GT line in the output window
(also counting what the camera never saw: hidden by vehicles, outside its field of view).
--lane-map also scores the lane map as training GT: `fhld autolabel --lane-map` makes the
output a training bag, bag_source builds its training windows (WINDOW_SETTINGS: the training
configs' 32 m windows of 10 sweeps, one per sweep) and each window's GT (the lane map, cut to
the window) is scored against the GT the simulator's own bag gives the same window (its
/lanes_gt, by the same rule). Two more rows split what the map misses: "seen" is every line
piece some image's labels show (/camera/lanes_gt of all images), so its R@30 is how much of a
window's lines the camera could ever label; "lifted" is every lane autolabel made (/lanes of
all images, unmerged), so lifted against map is what merging adds or loses.
Seeds AUTOLABEL_SEED_BASE.. are held out from training and from the detector's test set; the
sensor presets take turns.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fhld_ros.camera.labels2d import read_label_dir, write_labels
from fhld_ros.cli import main as fhld
from fhld_ros.data.bag_source import LabelledBag, bag_samples, label_at, read_labels
from fhld_ros.data.cache import TEST_SEED_BASE, CacheSettings
from fhld_ros.data.samples import lanes_in_window
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation.evaluate import evaluate_bags, summary
from fhld_ros.evaluation.metrics import PointCounts, point_counts
from fhld_ros.sim.lidar import SENSORS

AUTOLABEL_SEED_BASE = TEST_SEED_BASE + 500_000
VISIBLE_GT, ALL_GT = '/camera/lanes_gt', '/lanes_gt'
# the windows of config/train_*.yaml (800 px at 4 cm, 10 sweeps), one per sweep for more of them
WINDOW_SETTINGS = CacheSettings(size_px=800, resolution_m=0.04, sweeps_per_sample=10, stride=1)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--drives', type=int, default=8, help='held-out drives (default 8)')
    parser.add_argument('--first-drive', type=int, default=0, metavar='K',
                        help='start at drive K (seed AUTOLABEL_SEED_BASE + K; default 0)')
    parser.add_argument('--sweeps', type=int, default=30, help='sweeps per drive (default 30)')
    parser.add_argument('--perturb-px', type=float, default=0.0, metavar='P',
                        help='move every 2D label point by up to P px in u and v (default 0)')
    parser.add_argument('--lane-map', action='store_true',
                        help='also score the lane map (autolabel --lane-map) as training GT: '
                        'its training windows against the simulator\'s')
    parser.add_argument('--labels', choices=('simulator', 'salad'), default='simulator',
                        help="2D labels from the simulator (exact) or SALAD's lanes "
                             '(fhld salad-labels2d: pseudo-labels)')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def perturb_labels(src: Path, dst: Path, px: float, seed: int) -> None:
    """Copy the label files of src into dst with every point moved by U(-px, px) in u and v."""
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    for stamp, labels in sorted(read_label_dir(src).items()):
        for lane in labels.lanes:
            lane.uv = lane.uv + rng.uniform(-px, px, lane.uv.shape)
        write_labels(dst / f'{stamp}.json', labels)


def run_drive(work: Path, seed: int, sensor: str, sweeps: int, perturb_px: float,
              lane_map: bool = False, salad: bool = False
              ) -> tuple[list, list, float, MapScores | None]:
    """Frames scored against the visible and the full GT, autolabel's seconds and, with
    lane_map, the lane map's training windows scored (score_lane_map). salad: SALAD's lanes
    are the 2D labels instead of the simulator's."""
    bag, labels, lanes = work / 'drive', work / 'labels2d', work / 'autolabel'
    quiet = ['--quiet']
    if fhld(['simulate', str(bag), '--seed', str(seed), '--sweeps', str(sweeps), '--sensor',
             sensor, '--camera', '--labels2d', str(labels), *quiet]) != 0:
        raise ConfigError(f'fhld simulate failed for seed {seed}')
    if salad:
        labels = work / 'salad2d'
        if fhld(['salad-labels2d', str(bag), str(labels), *quiet]) != 0:
            raise ConfigError(f'fhld salad-labels2d failed for seed {seed}')
    if perturb_px > 0:
        perturb_labels(labels, work / 'perturbed', perturb_px, seed)
        labels = work / 'perturbed'
    start = time.perf_counter()
    if fhld(['autolabel', str(bag), str(lanes), '--labels2d', str(labels), *quiet,
             *(['--lane-map'] if lane_map else [])]) != 0:
        raise ConfigError(f'fhld autolabel failed for seed {seed}')
    seconds = time.perf_counter() - start
    args = {topic: argparse.Namespace(pred_bag=str(lanes), gt_bag=str(bag), pred_topic='/lanes',
                                      gt_topic=topic, once_official=False, score_thresh=0.1)
            for topic in (VISIBLE_GT, ALL_GT)}
    return (evaluate_bags(args[VISIBLE_GT]), evaluate_bags(args[ALL_GT]), seconds,
            score_lane_map(lanes, bag) if lane_map else None)


def run(args: argparse.Namespace) -> int:
    if args.drives < 1 or args.sweeps < 1 or args.first_drive < 0:
        raise ConfigError('--drives and --sweeps must be >= 1, --first-drive >= 0')
    if not 0 <= args.perturb_px <= 50:
        raise ConfigError(f'--perturb-px must be within 0..50, got {args.perturb_px:g}')
    sensors = list(SENSORS)
    visible, full, seconds, maps = [], [], [], MapScores()
    with tempfile.TemporaryDirectory(prefix='fhld-autolabel-eval-') as tmp:
        for k in range(args.first_drive, args.first_drive + args.drives):
            seed, sensor = AUTOLABEL_SEED_BASE + k, sensors[k % len(sensors)]
            work = Path(tmp) / f'drive_{k}'
            work.mkdir()
            v, f, s, m = run_drive(work, seed, sensor, args.sweeps, args.perturb_px,
                                   args.lane_map, args.labels == 'salad')
            visible += v
            full += f
            seconds.append(s)
            one = summary(v)['point']
            lane_map = '' if m is None else \
                f', lane map F1@10 {m.map.scores()["F1@10"]:.1f} of windows\' true GT'
            print(f'drive {k} (seed {seed}, {sensor}): {len(v)} images, F1@10 '
                  f'{one["F1@10"]:.1f}, F1@30 {one["F1@30"]:.1f}, autolabel {s:.1f} s'
                  f'{lane_map}', file=sys.stderr)
            maps += m or MapScores()
    result = {'drives': args.drives, 'first_drive': args.first_drive, 'sweeps': args.sweeps,
              'labels': args.labels, 'perturb_px': args.perturb_px,
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
    if args.lane_map:
        result['lane_map'] = _print_lane_map(maps.summary())
    if args.json:
        print(json.dumps(result))
    return 0


@dataclasses.dataclass
class MapScores:
    """Point counts against the true GT of the training windows of one or more drives: of the
    lane map's GT (map), of all lanes autolabel lifted (lifted) and of all GT the labels show
    (seen); per window the R@30 of each."""

    map: PointCounts = dataclasses.field(default_factory=PointCounts)
    lifted: PointCounts = dataclasses.field(default_factory=PointCounts)
    seen: PointCounts = dataclasses.field(default_factory=PointCounts)
    window_recall: list = dataclasses.field(default_factory=list)  # [(map, lifted, seen)]

    def __add__(self, other: MapScores) -> MapScores:
        return MapScores(self.map + other.map, self.lifted + other.lifted,
                         self.seen + other.seen, self.window_recall + other.window_recall)

    def summary(self) -> dict:
        recall = np.array(self.window_recall).reshape(-1, 3)
        rows = ('map', 'lifted', 'seen')
        return {'windows': len(recall),
                **{name: getattr(self, name).scores() for name in rows},
                'window_R@30': {name: {'mean': float(col.mean()), 'median': float(np.median(col)),
                                       'min': float(col.min())}
                                for name, col in zip(rows, recall.T)} if len(recall) else {}}


def score_lane_map(map_bag: Path, sim_bag: Path,
                   settings: CacheSettings = WINDOW_SETTINGS) -> MapScores:
    """The training windows of map_bag (bag_source) scored against the GT the simulator's bag
    gives the same windows, and the seen GT (see the module doc)."""
    truth = read_labels(sim_bag, ALL_GT)
    stamps = np.array([t.stamp_ns for t in truth], dtype=np.int64)
    lifted, seen = ([lane for labels in read_labels(bag, topic) for lane in labels.lanes]
                    for bag, topic in ((map_bag, '/lanes'), (sim_bag, VISIBLE_GT)))
    half = settings.size_px * settings.resolution_m / 2
    out = MapScores()
    for window in bag_samples(LabelledBag(str(map_bag)), settings):
        label = label_at(truth, stamps, window.meta['stamp_ns']) or truth[0]
        true = lanes_in_window(label.lanes, window.window_to_odom, half)[0]
        counts = [point_counts(lanes, true) for lanes in (
            window.lanes, *(lanes_in_window(pool, window.window_to_odom, half)[0]
                            for pool in (lifted, seen)))]
        out += MapScores(*counts, [tuple(c.scores()['R@30'] for c in counts)])
    return out


def _print_lane_map(result: dict) -> dict:
    """The lane map's table (score_lane_map) printed; result returned."""
    print(f'lane map as training GT, against the true GT of {result["windows"]} windows '
          f'({WINDOW_SETTINGS.size_px * WINDOW_SETTINGS.resolution_m:g} m, '
          f'{WINDOW_SETTINGS.sweeps_per_sample} sweeps):')
    for name, title in (('map', 'lane map'), ('lifted', 'lifted, unmerged'),
                        ('seen', 'seen by camera')):
        p = result[name]
        print(f'  {title:<16} F1@10 {p["F1@10"]:6.2f}  F1@30 {p["F1@30"]:6.2f}  '
              f'(P@10 {p["P@10"]:.2f} R@10 {p["R@10"]:.2f} P@30 {p["P@30"]:.2f} '
              f'R@30 {p["R@30"]:.2f})')
    for name, title in (('map', 'the map covers'), ('seen', 'the camera saw')):
        r = result['window_R@30'].get(name)
        if r:
            print(f'  of a window\'s true lines {title} (R@30): mean {r["mean"]:.1f} %, '
                  f'median {r["median"]:.1f} %, min {r["min"]:.1f} %')
    return result
