"""`fhld replay IN_BAG OUT_BAG`: the node's pipeline on bag time, as fast as the machine allows.

The detection timer runs on sensor stamps: it fires every 1/rate_hz seconds of bag time, so a
replay gives the same lanes on any machine (deterministic), unlike a live run that may skip.
OUT_BAG follows bagio's output rule: an existing one is refused unless --overwrite (then only a
bag folder is replaced), and one equal to, inside or containing IN_BAG always.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from tqdm import tqdm

from fhld_ros.bagio import BagWriter, check_output, read_messages, topic_counts
from fhld_ros.detectors import make_detector
from fhld_ros.errors import ConfigError
from fhld_ros.parameters import DetectorParams, load_params_yaml
from fhld_ros.pipeline import LanePipeline
from msg_adapters.family import stamp_to_ns
from msg_adapters.lanes import lane_to_path_cdr, lanes_to_marker_array_cdr


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('in_bag', type=Path, help='rosbag2 bag with PointCloud2 (+ Odometry)')
    parser.add_argument('out_bag', type=Path, help='MCAP bag to write /lanes and ego Paths to')
    parser.add_argument('--points-topic', default='/points')
    parser.add_argument('--odom-topic', default='/odom',
                        help="odometry topic; '' or a topic absent from the bag: per sweep")
    parser.add_argument('--params', type=Path, help='lane_detector parameter YAML')
    parser.add_argument('--checkpoint', help='FHLD weights (default: the shipped checkpoint)')
    parser.add_argument('--detector', choices=['fhld', 'classical'],
                        help='detector back-end (default: the parameter, fhld)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing OUT_BAG (only a rosbag2 bag folder)')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def replay(in_bag: Path, out_bag: Path, params: DetectorParams, points_topic: str = '/points',
           odom_topic: str = '/odom', progress: bool = True,
           overwrite: bool = False) -> dict[str, int]:
    """Run the pipeline over in_bag and write its outputs to out_bag; returns counters."""
    inputs = {'IN_BAG': in_bag}
    check_output(out_bag, overwrite, inputs)  # before the model loads: fail fast
    counts = topic_counts(in_bag)
    if points_topic not in counts:
        raise ConfigError(f'bag {in_bag} has no topic {points_topic} (it has: '
                          f'{", ".join(sorted(counts)) or "nothing"})')
    if counts[points_topic] == 0:
        raise ConfigError(f'bag {in_bag} has no messages on {points_topic}')
    topics = [points_topic] + ([odom_topic] if odom_topic in counts else [])
    has_odometry = counts.get(odom_topic, 0) > 0
    pipeline = LanePipeline(params, make_detector(params), expect_odometry=has_odometry)
    period_ns = round(1e9 / params.rate_hz)
    lanes_topic = '/' + params.lanes_topic.strip('/')
    next_tick: int | None = None
    stats = {'sweeps': 0, 'dropped': 0, 'detections': 0}
    bar = tqdm(total=sum(counts[t] for t in topics), unit='msg', disable=not progress,
               desc='replay', file=sys.stderr)
    with BagWriter(out_bag, overwrite, inputs) as writer:
        def publish(out) -> None:
            writer.write(lanes_topic, 'visualization_msgs/msg/MarkerArray', out.stamp_ns,
                         lanes_to_marker_array_cdr(out.stamp_ns, out.frame_id, out.lanes,
                                                   out.confidences, out.ids, out.outline))
            for side, lane in (('ego_left', out.ego_left), ('ego_right', out.ego_right)):
                writer.write(f'{lanes_topic}/{side}', 'nav_msgs/msg/Path', out.stamp_ns,
                             lane_to_path_cdr(out.stamp_ns, out.frame_id, lane))
            stats['detections'] += 1

        def timer() -> None:
            """The detection timer, firing on the stamps of the sweeps in the grid."""
            nonlocal next_tick
            newest = pipeline.grid.newest_stamp_ns
            if newest is None:
                return
            if next_tick is None or newest < next_tick - period_ns:
                next_tick = newest  # first sweep, or time went back (the grid reset too)
            while newest >= next_tick:
                out = pipeline.detect()
                if out is not None:
                    publish(out)
                next_tick += period_ns

        def dropped(stamp_ns: int, exc: ValueError) -> None:
            stats['dropped'] += 1
            bar.write(f'dropped cloud at {stamp_ns * 1e-9:.3f} s: {exc}')

        for topic, _, msg in read_messages(in_bag, topics):
            bar.update()
            if topic == points_topic:
                try:
                    pipeline.add_cloud(msg)
                    stats['sweeps'] += 1
                except ValueError as exc:
                    dropped(stamp_to_ns(msg.header.stamp), exc)
            else:
                pipeline.add_odometry(msg)
            timer()
        # the bag ended before the odometry of its last sweeps: they go in one at a time
        # (per sweep where no odometry covers them), each on the timer as before
        while pipeline.insert_waiting():
            timer()
    bar.close()
    if pipeline.counters['clouds_without_odometry']:  # sweeps detected alone, in their frame
        stats['without_odometry'] = pipeline.counters['clouds_without_odometry']
    return stats


def run(args: argparse.Namespace) -> int:
    check_output(args.out_bag, args.overwrite, {'IN_BAG': args.in_bag})
    params = load_params_yaml(args.params) if args.params else DetectorParams()
    overrides = {k: v for k, v in (('detector', args.detector),
                                   ('checkpoint', args.checkpoint)) if v}
    params = dataclasses.replace(params, **overrides)
    stats = replay(args.in_bag, args.out_bag, params, args.points_topic, args.odom_topic,
                   progress=not args.quiet, overwrite=args.overwrite)
    alone = (f', {stats["without_odometry"]} without odometry (detected alone)'
             if stats.get('without_odometry') else '')
    print(f'replayed {stats["sweeps"]} sweeps ({stats["dropped"]} dropped{alone}), '
          f'{stats["detections"]} detections -> {args.out_bag}')
    return 0
