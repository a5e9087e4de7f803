"""`fhld demo` (what `make demo` runs): simulate a drive, detect lanes on it, score, draw.

Writes into --out: sim/ (the simulated MCAP bag), lanes/ (the detector's /lanes MCAP bag, for
Foxglove or RViz through a bag player), metrics.json and demo.png (BEV intensity with GT and
predicted lanes of one frame). --out may exist and hold other files, which are never touched;
those four outputs in it are refused when present unless --overwrite, which replaces sim/ and
lanes/ only when they are rosbag2 bag folders and the two files only when they are regular
files (bagio's output rule). Everything is checked before anything is written.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from fhld_ros.bagio import check_file_output, check_output, read_messages, write_file_atomically
from fhld_ros.cli import main as fhld
from fhld_ros.commands.replay import replay
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation.evaluate import Frame, draw_top_view, evaluate_bags, summary
from fhld_ros.model.checkpoint import DEFAULT_CHECKPOINT
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import LanePipeline
from fhld_ros.rolling_grid import BevWindow
from msg_adapters.family import stamp_to_ns


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--out', type=Path, default=Path('out/demo'), help='output directory')
    parser.add_argument('--seed', type=int, default=7, help='scene seed')
    parser.add_argument('--sweeps', type=int, default=80, help='10 Hz sweeps to simulate')
    parser.add_argument('--detector', choices=['fhld', 'classical'], default='fhld')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the sim/, lanes/, metrics.json and demo.png of an '
                        'earlier demo in --out (nothing else there is touched)')


def check_out_dir(out: Path, overwrite: bool) -> None:
    """ConfigError unless the demo may write its four outputs into out (see the module doc)."""
    if not (out.exists() or out.is_symlink()):
        return  # created with its parents; nothing in it to replace
    if not out.is_dir():
        raise ConfigError(f'--out {out} exists and is not a folder')
    for name in ('sim', 'lanes'):
        check_output(out / name, overwrite, label='demo output')
    for name in ('metrics.json', 'demo.png'):
        check_file_output(out / name, overwrite, label='demo output')


def _window_at(bag: Path, stamp_ns: int, params: DetectorParams) -> BevWindow:
    """The BEV window the pipeline saw when its newest sweep had stamp_ns."""
    pipeline = LanePipeline(params, detector=lambda window: ([], np.zeros(0)))
    for topic, _, msg in read_messages(bag, ['/points', '/odom']):
        if topic == '/odom':
            pipeline.add_odometry(msg)
        elif stamp_to_ns(msg.header.stamp) <= stamp_ns:
            pipeline.add_cloud(msg)
        else:
            break
    return pipeline.take_window()


def draw(frame: Frame, window: BevWindow, path: Path, title: str) -> None:
    """BEV mean intensity with GT (green) and predicted (red) lanes, forward up."""
    draw_top_view(path, frame.gt, frame.pred, window.spec.length_m / 2, title,
                  background=window.raster[0])


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.sweeps <= 1000:
        raise ConfigError(f'--sweeps must be in 1..1000, got {args.sweeps}')
    out = args.out
    check_out_dir(out, args.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    sim, lanes = out / 'sim', out / 'lanes'
    detector = args.detector
    if detector == 'fhld' and not DEFAULT_CHECKPOINT.exists():
        print(f'note: no trained weights at {DEFAULT_CHECKPOINT}; using the classical baseline')
        detector = 'classical'
    params = dataclasses.replace(DetectorParams(), detector=detector)

    start = time.monotonic()
    print(f'[1/4] simulating {args.sweeps} sweeps (seed {args.seed}) -> {sim}')
    status = fhld(['simulate', str(sim), '--seed', str(args.seed), '--sweeps', str(args.sweeps),
                   '--quiet'] + (['--overwrite'] if args.overwrite else []))
    if status:
        return status
    print(f'[2/4] detecting lanes with {detector} -> {lanes}')
    stats = replay(sim, lanes, params, overwrite=args.overwrite)
    print(f'      {stats["sweeps"]} sweeps, {stats["detections"]} detections')
    print('[3/4] scoring against /lanes_gt')
    eval_args = argparse.Namespace(pred_bag=str(lanes), gt_bag=str(sim), pred_topic='/lanes',
                                   gt_topic='/lanes_gt', once_official=False, score_thresh=0.1)
    frames = evaluate_bags(eval_args)
    result = summary(frames)
    write_file_atomically(out / 'metrics.json',
                          lambda tmp: tmp.write_text(json.dumps(result, indent=2)))
    point, once = result['point'], result['once']
    print(f'      {len(frames)} frames   within 10 cm: P {point["P@10"]:.1f} R '
          f'{point["R@10"]:.1f} F1 {point["F1@10"]:.1f}   within 30 cm: F1 {point["F1@30"]:.1f}')
    print(f'      ONCE-3DLanes: P {once["P"]:.1f} R {once["R"]:.1f} F1 {once["F1"]:.1f} '
          f'CD {once["CD"]:.3f} m')
    print(f'[4/4] drawing {out / "demo.png"}')
    frame = max(frames[len(frames) // 2:], key=lambda f: len(f.gt))  # a busy frame, warmed up
    window = _window_at(sim, frame.stamp_ns, params)
    scores = frame.point.scores()
    title = (f'fhld demo: seed {args.seed}, {detector}, frame t={frame.stamp_ns * 1e-9:.1f} s\n'
             f'F1@10cm {scores["F1@10"]:.1f}  F1@30cm {scores["F1@30"]:.1f}')
    write_file_atomically(out / 'demo.png', lambda tmp: draw(frame, window, tmp, title))
    print(f'done in {time.monotonic() - start:.0f} s: {out}/ (sim, lanes, metrics.json, '
          'demo.png)')
    return 0
