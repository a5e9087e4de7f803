"""`fhld salad-eval`: SALAD scored with the ONCE-3DLanes metric on held-out simulated drives
(SALAD's test seeds, each with its own camera) and, when given, ONCE-3DLanes or OpenLane
files.

Rows as in the paper's Table 2: F1, precision, recall and the CD error of the true positives
at tau_CD 0.15, 0.30 and 0.50 m (the paper's definition: top-view IoU >= 0.3, then the
unilateral chamfer distance), the released evaluator's figures at 0.30 m ("official"), and the
error by range ("by_range": over the GT points of every compared pair, the distance to the
predicted lane, per 10 m of forward distance; where the far range loses it). `--perfect`
replaces heads by their targets (perfect_maps.py), to see which head the F1 is lost in.
`--road-plane M` gives the near lanes their depth from the road under the camera where the
source knows its mount (the simulator's drives; road_plane.py), up to M metres: SALAD with a
known mount, not the paper's SALAD (`--road-pitch image`: the mount's height, each image's
own pitch, where the network's road is off that height; lanes_road.py). `--camera-height M`
moves every drive's camera to M metres over the road (each keeps its pitch and lens; `LOW
HIGH`: a range): how a mount outside the training range (1.2-2.0 m) fares.
Lanes are compared in a camera-centred top view (metrics.py takes x forward, y left, z up:
the optical frame turned, not moved), HALF_SIZE_M ahead and to each side: the GT is scored
within it (clipped), the range SALAD decodes (SaladConfig.max_depth_m) and the simulated GT
keeps. Real labels run further (OpenLane's to 67-122 m), and the unilateral chamfer distance of
a lane labelled to 120 m would count its last 60 m against any lane decoded to 60 m.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fhld_ros.errors import ConfigError
from fhld_ros.evaluation.metrics import (
    SAMPLE_STEP,
    LaneCounts,
    clip_lanes_to_square,
    lane_counts,
    once_counts_official,
    once_matches,
)
from fhld_ros.geometry import resample_polyline
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT
from fhld_ros.salad.detector import SaladDetector, add_decoding_arguments, decoding_options
from fhld_ros.salad.once_format import read_once
from fhld_ros.salad.openlane_format import read_openlane
from fhld_ros.salad.perfect_maps import HEADS, PerfectMaps
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import (
    SEEDS_OWN,
    DriveVariant,
    add_variant_arguments,
    drive_variant,
    salad_seeds,
    simulated_samples,
)

TAUS = (0.15, 0.30, 0.50)
HALF_SIZE_M = 60.0  # the top view compared (and the GT scored): 60 m ahead, to each side
RANGE_EDGES_M = np.arange(0.0, 61.0, 10.0)
RANGE_STEP_M = 0.1  # GT points this far apart for the error by range


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--checkpoint', type=Path, default=DEFAULT_SALAD_CHECKPOINT)
    add_labelled_image_arguments(parser, 10, 5, 0, "the split's drives from this one (e.g. a "
                                 'second validation set to confirm a choice made on the first)')
    parser.add_argument('--validation', action='store_true',
                        help="SALAD's validation seeds instead of its test seeds (for choosing "
                             'settings and checkpoints)')
    parser.add_argument('--perfect', nargs='+', choices=HEADS, default=[], metavar='HEAD',
                        help='replace these heads (seg, offsets, depth) by the targets of the '
                             "images' GT lanes: what F1 would be with them perfect")
    parser.add_argument('--flip-average', action=argparse.BooleanOptionalAction, default=False,
                        help="the mean of the network's maps of the image and its mirror image "
                             '(default: one pass, as the node)')
    parser.add_argument('--no-road-profile', dest='road_profile', action='store_false',
                        help="the network's depths as they are, not pulled towards one road "
                             'depth per image row')
    add_decoding_arguments(parser)
    parser.add_argument('--road-plane', type=float, default=0.0, metavar='M',
                        help="the near lanes' depth from the road plane of the camera's known "
                             'mount (simulated drives), up to M metres (0: off; 20 chosen on '
                             'the validation images)')
    parser.add_argument('--road-pitch', choices=('mount', 'image'), default='mount',
                        help="with --road-plane, the road's pitch from the mount, or from each "
                             "image's own lanes where the network's road is off the mount's "
                             'height (lanes_road.py)')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def optical_to_window(lane: np.ndarray) -> np.ndarray:
    """Optical frame (x right, y down, z forward) -> x forward, y left, z up."""
    return np.column_stack([lane[:, 2], -lane[:, 0], -lane[:, 1]])


def score(detector: SaladDetector, samples: Iterable[CameraLaneSample],
          road_until_m: float = 0.0, pitch_from_image: bool = False) -> dict[str, dict]:
    """Counts summed over the samples, as score rows: 'tau_0.15' ... and 'official', and the
    error by range ('by_range'); road_until_m > 0: with each sample's road plane (if it has
    one) up to that depth, its pitch the image's own with pitch_from_image."""
    counts = {tau: LaneCounts() for tau in TAUS}
    official, images = LaneCounts(official=True), 0
    errors: list[np.ndarray] = []  # (n, 2): GT point's forward distance, error
    for sample in samples:
        road = (dataclasses.replace(sample.road, until_m=road_until_m,
                                    pitch_from_image=pitch_from_image)
                if road_until_m > 0 and sample.road is not None else None)
        lanes, scores = detector(sample.image, sample.intrinsics, road, sample.distortion)
        pred = [optical_to_window(lane) for lane in lanes]
        gt = clip_lanes_to_square([optical_to_window(lane) for lane in sample.lanes
                                   if len(lane) >= 2], HALF_SIZE_M)
        matches = once_matches(pred, gt, HALF_SIZE_M)  # one assignment for every tau
        for tau in TAUS:
            counts[tau] = counts[tau] + lane_counts(matches, len(pred), len(gt), tau)
        official = official + once_counts_official(pred, scores, gt)
        errors += [_point_errors(gt[g], pred[p]) for g, p, _ in matches]
        images += 1
    rows = {f'tau_{tau:.2f}': c.scores() for tau, c in counts.items()}
    rows['official'] = official.scores()
    for row, c in zip(rows.values(), [*counts.values(), official]):
        row.update(images=images, gt=c.n_gt, pred=c.n_pred)
    rows['by_range'] = _by_range(np.concatenate(errors) if errors else np.zeros((0, 2)))
    return rows


def _point_errors(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(n, 2): each GT point's forward distance and its 3D distance to the predicted lane."""
    points = resample_polyline(gt, RANGE_STEP_M)
    distance, _ = cKDTree(resample_polyline(pred, SAMPLE_STEP)).query(points)
    return np.column_stack([points[:, 0], distance])


def _by_range(errors: np.ndarray) -> dict[str, dict]:
    band = np.digitize(errors[:, 0], RANGE_EDGES_M) - 1
    out = {}
    for i, (lo, hi) in enumerate(zip(RANGE_EDGES_M[:-1], RANGE_EDGES_M[1:])):
        e = errors[band == i, 1]
        out[f'{lo:.0f}-{hi:.0f}m'] = {  # None where no GT point lies: JSON has no NaN
            'median_m': float(np.median(e)) if len(e) else None,
            'mean_m': float(e.mean()) if len(e) else None, 'points': int(len(e))}
    return out


def held_out_drives(drives: int, frames: int, split: str = 'test',
                    variant: DriveVariant = SEEDS_OWN, first: int = 0,
                    workers: int = 1) -> Iterator[CameraLaneSample]:
    """The images of the split's drives, in seed order; rendered by `workers` processes
    (ahead of the scoring, which runs in this one) when more than one."""
    jobs = [(seed, frames, variant) for seed in salad_seeds(split, drives, first)]
    if workers <= 1:
        for job in jobs:
            yield from _drive_samples(job)
        return
    with multiprocessing.Pool(workers) as pool:  # leaving it terminates the workers
        for samples in pool.imap(_drive_samples, jobs):
            yield from samples


def _drive_samples(job: tuple[int, int, DriveVariant]) -> list[CameraLaneSample]:
    seed, frames, variant = job
    return list(simulated_samples(seed, frames, variant=variant))


def add_labelled_image_arguments(parser: argparse.ArgumentParser, drives: int, frames: int,
                                 first_drive: int, first_drive_help: str) -> None:
    """The options labelled_images reads, with the commands' own defaults: --drives,
    --frames, --first-drive, the drives' variant, --workers, --once [--once-split],
    --openlane."""
    parser.add_argument('--drives', type=int, default=drives,
                        help='held-out simulated drives (0: none)')
    parser.add_argument('--frames', type=int, default=frames, help='images per drive, 1 s apart')
    parser.add_argument('--first-drive', type=int, default=first_drive, help=first_drive_help)
    add_variant_arguments(parser)
    parser.add_argument('--workers', type=int, default=1,
                        help='processes rendering the simulated drives (the same images at any '
                             'number)')
    parser.add_argument('--once', type=Path, metavar='ROOT', help='an ONCE-3DLanes folder')
    parser.add_argument('--once-split', default='val')
    parser.add_argument('--openlane', type=Path, metavar='ROOT', help='an OpenLane folder')


def labelled_images(args: argparse.Namespace, drives_name: str, split: str,
                    variant: DriveVariant) -> dict[str, Iterable[CameraLaneSample]]:
    """The labelled images the options name, by source: the split's simulated drives (--drives
    from --first-drive, as drives_name), an ONCE-3DLanes (--once) and an OpenLane (--openlane)
    folder."""
    if args.drives < 0 or args.first_drive < 0 or args.frames < 1 or args.workers < 1:
        raise ConfigError('--drives and --first-drive must be >= 0, --frames and --workers >= 1')
    sources: dict[str, Iterable[CameraLaneSample]] = {}
    if args.drives:
        sources[drives_name] = held_out_drives(args.drives, args.frames, split, variant,
                                               args.first_drive, args.workers)
    if args.once:
        sources['once'] = read_once(args.once, args.once_split)
    if args.openlane:
        sources['openlane'] = read_openlane(args.openlane)
    return sources


def _print(name: str, rows: dict[str, dict]) -> None:
    first = next(iter(rows.values()))
    print(f'{name}: {first["images"]} images, {first["gt"]} GT lanes')
    for key, r in rows.items():
        if key != 'by_range':
            print(f'  {key:10s} F1 {r["F1"]:5.1f}  P {r["P"]:5.1f}  R {r["R"]:5.1f}  '
                  f'CD {r["CD"]:.3f} m')
    print('  error by range (GT points of compared pairs to the prediction), median / mean m:')
    print('  ' + '  '.join(f'{band} {r["median_m"]:.2f} / {r["mean_m"]:.2f}' if r['points']
                           else f'{band} -' for band, r in rows['by_range'].items()))


def run(args: argparse.Namespace) -> int:
    if args.road_plane < 0:
        raise ConfigError(f'--road-plane must be >= 0, got {args.road_plane:g}')
    variant = drive_variant(args)
    detector = SaladDetector(args.checkpoint, flip_average=args.flip_average,
                             road_profile=args.road_profile, **decoding_options(args))
    perfect = PerfectMaps(detector, args.perfect) if args.perfect else None
    sources = labelled_images(args, 'validation' if args.validation else 'simulated',
                              'val' if args.validation else 'test', variant)
    if not sources:
        raise ConfigError('nothing to score: --drives 0 and no --once / --openlane')
    results, image_pitch = {}, args.road_pitch == 'image'
    for name, samples in sources.items():
        results[name] = (score(perfect, perfect.over(samples), args.road_plane, image_pitch)
                         if perfect else score(detector, samples, args.road_plane, image_pitch))
        _print(f'{name} (perfect {", ".join(args.perfect)})' if perfect else name,
               results[name])
    if args.json:
        json.dump(results, sys.stdout)
        print()
    return 0
