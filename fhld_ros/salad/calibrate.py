"""`fhld salad-calibrate`: the network's depth measured against GT lanes on held-out images,
written into a copy of the weights as their depth calibration (SaladConfig.depth_calibration_*).

The simulator labels lanes to max_depth_m (60 m), so training never shows the network a lane
beyond it, and near it the network's depth falls short: on the validation drives, at GT lane
cells, by a median 1-2 % at 40-50 m and 4-5 % at 50-55 m of the network's depth, on every set
and road look alike (docs/salad.md, "The far depth calibrated"). At 55 m, 4 % of the depth
moves a line 7 m to the side by 0.3 m, the metric's tau. The decoding multiplies each cell's
depth by the gain measured at its depth.

The measurement: every GT lane cell (targets.lane_targets) the network marks as a lane, binned
by the network's depth (BIN_M deep), the median of log(true / network depth) per bin with
MIN_CELLS or more, at the bin's median network depth. Simulated images come from SALAD's
validation seeds only (from --first-drive; the first 300 drives are the ones settings are
chosen and confirmed on); a user's own labelled images (--once, --openlane) calibrate the weights
to their camera.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from fhld_ros.bagio import check_file_output
from fhld_ros.errors import ConfigError
from fhld_ros.salad.checkpoint import resolve_salad_checkpoint, save_salad
from fhld_ros.salad.config import SaladConfig, uncalibrated
from fhld_ros.salad.detector import SaladDetector
from fhld_ros.salad.evaluate import add_labelled_image_arguments, labelled_images
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import drive_variant
from fhld_ros.salad.targets import lane_targets

BIN_M = 5.0
MIN_CELLS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('checkpoint', type=Path, help='SALAD weights (a path or shipped name)')
    parser.add_argument('out', type=Path, help='the calibrated copy to write')
    add_labelled_image_arguments(parser, 150, 2, 300, 'the first validation drive (default '
                                 '300: past the drives that `salad-eval --validation` chooses '
                                 'and confirms settings on)')
    parser.add_argument('--overwrite', action='store_true', help='overwrite OUT if it exists')


def depth_ratios(detector: SaladDetector, samples: Iterable[CameraLaneSample]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(network depth, log(true / network depth)) at every GT lane cell of the samples that the
    network marks as a lane, uncalibrated; depth the calibration applies to."""
    cfg = detector.cfg
    network, log_ratio = [], []
    for sample in samples:
        prob, spatial = detector.maps(sample.image, sample.intrinsics, sample.distortion)
        target = lane_targets(sample.lanes, cfg.camera)
        cells = (target.seg > 0) & target.depth_mask & (prob > cfg.seg_threshold)
        rows, _ = np.nonzero(cells)
        z = cfg.network_depth(rows, spatial[2][cells])
        ok = z > 0
        network.append(z[ok])
        log_ratio.append(np.log(target.depth[cells][ok] / z[ok]))
    if not network:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(network), np.concatenate(log_ratio)


def calibration(network: np.ndarray, log_ratio: np.ndarray, max_depth_m: float
                ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(depths, log gains) of the calibration: per BIN_M of network depth up to max_depth_m
    with MIN_CELLS cells or more, the bin's median depth and median log ratio."""
    knots, gains = [], []
    for low in np.arange(0.0, max_depth_m, BIN_M):
        inside = (network >= low) & (network < low + BIN_M)
        if np.count_nonzero(inside) >= MIN_CELLS:
            knots.append(float(np.median(network[inside])))
            gains.append(float(np.median(log_ratio[inside])))
    if not knots:
        raise ConfigError(f'too few lane cells to calibrate on ({len(network)}; {MIN_CELLS} '
                          f'per {BIN_M:g} m of depth): more images')
    return tuple(knots), tuple(gains)


def run(args: argparse.Namespace) -> int:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    check_file_output(args.out, args.overwrite,
                      {'CHECKPOINT': resolve_salad_checkpoint(args.checkpoint)}, 'OUT')
    detector = SaladDetector(args.checkpoint)
    detector.cfg = uncalibrated(detector.cfg)
    sources = labelled_images(args, 'validation drives', 'val', drive_variant(args))
    if not sources:
        raise ConfigError('nothing to calibrate on: --drives 0 and no --once / --openlane')
    measured = [depth_ratios(detector, samples) for samples in sources.values()]
    network, log_ratio = (np.concatenate(parts) for parts in zip(*measured))
    knots, gains = calibration(network, log_ratio, detector.cfg.max_depth_m)
    cfg = dataclasses.replace(detector.cfg, depth_calibration_m=knots,
                              depth_calibration_log_gain=gains)
    cfg.validate('the measured calibration')
    _write(args, detector, cfg, list(sources), len(network))
    for knot, gain in zip(knots, gains):
        print(f'  network depth {knot:5.1f} m: true depth {100 * np.expm1(gain):+.1f} %')
    return 0


def _write(args: argparse.Namespace, detector: SaladDetector, cfg: SaladConfig,
           sources: list[str], cells: int) -> None:
    """The detector's weights with cfg to args.out, their provenance kept, the calibration's
    added to their meta."""
    model, info = detector.model, detector.info
    model.cfg = cfg
    meta = {**info.get('meta', {}), 'calibrated': {
        'checkpoint': str(args.checkpoint), 'command': ' '.join(sys.argv), 'sources': sources,
        'lane_cells': cells}}
    save_salad(args.out, model, info.get('train_command', ''), meta)
    print(f'wrote {args.out}: the depth calibrated on {cells} lane cells of the '
          f'{", ".join(sources)}')
