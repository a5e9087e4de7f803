"""`fhld replay IN_BAG OUT_BAG`: the node's pipeline on bag time, as fast as the machine allows.

`--detector salad` replays the camera images instead, through camera_lane_detector's pipeline
(commands/replay_camera.py); what follows is the LiDAR replay.

A thin driver of LanePipeline, as the node is: the pipeline decides which sweeps are detected
(rate_hz on sweep stamps), drops bad messages and builds the messages written, so a replay
writes what the node publishes when each message is handled before the next arrives, and the
same on any machine (a live node may skip sweeps while it is busy). What only a live node does:
let sweeps in when no message at all comes (the wall clock), and extrapolate poses DDS lost.
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
from fhld_ros.commands import replay_camera
from fhld_ros.commands.replay_camera import CAMERA_INFO_TOPIC, IMAGE_TOPIC, stamp_s
from fhld_ros.detectors import make_detector
from fhld_ros.errors import ConfigError
from fhld_ros.lane_output import LANE_TOPICS, lane_messages
from fhld_ros.parameters import DetectorParams, load_params_yaml
from fhld_ros.pipeline import LanePipeline


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('in_bag', type=Path, help='rosbag2 bag with PointCloud2 (+ Odometry), '
                        'or with Image + CameraInfo for --detector salad')
    parser.add_argument('out_bag', type=Path, help='MCAP bag to write /lanes and ego Paths to')
    parser.add_argument('--points-topic', default='/points')
    parser.add_argument('--odom-topic', default='/odom',
                        help="odometry topic; '' or a topic absent from the bag: per sweep")
    parser.add_argument('--image-topic', default=IMAGE_TOPIC,
                        help='--detector salad: images (Image; CompressedImage JPEG or PNG on '
                        'its /compressed topic where the bag has only that)')
    parser.add_argument('--camera-info-topic', default=CAMERA_INFO_TOPIC,
                        help='--detector salad: their camera_info')
    parser.add_argument('--params', type=Path, help='lane_detector parameter YAML (with '
                        '--detector salad: its camera_lane_detector section)')
    parser.add_argument('--checkpoint', help='FHLD (SALAD with --detector salad) weights '
                        '(default: the shipped checkpoint)')
    parser.add_argument('--detector', choices=['fhld', 'classical', 'salad'],
                        help="detector back-end (default: the parameter, fhld); 'salad': the "
                        'camera detector on --image-topic')
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
    lanes_topic = '/' + params.lanes_topic.strip('/')
    detections = 0
    bar = tqdm(total=sum(counts[t] for t in topics), unit='msg', disable=not progress,
               desc='replay', file=sys.stderr)
    with BagWriter(out_bag, overwrite, inputs) as writer:
        def detect_due() -> None:
            nonlocal detections
            while (out := pipeline.detect()) is not None:
                for suffix, cdr in lane_messages(out).items():
                    writer.write(lanes_topic + suffix, LANE_TOPICS[suffix], out.stamp_ns, cdr)
                detections += 1

        for topic, _, msg in read_messages(in_bag, topics):
            bar.update()
            cloud = topic == points_topic
            intake = pipeline.receive_cloud(msg) if cloud else pipeline.receive_odometry(msg)
            if intake.dropped is not None:
                bar.write(f'dropped {"cloud" if cloud else "odometry"} at {stamp_s(msg)}: '
                          f'{intake.dropped}')
            detect_due()
        # the bag ended before the odometry of its last sweeps: they go in one at a time
        # (per sweep where no odometry covers them)
        while pipeline.insert_waiting():
            detect_due()
    bar.close()
    counters = pipeline.counters
    stats = {'sweeps': counters['clouds'],
             'dropped': counters['bad_clouds'], 'detections': detections}
    for key, name in (('clouds_without_odometry', 'without_odometry'),  # detected alone
                      ('bad_odometry', 'bad_odometry')):
        if counters[key]:
            stats[name] = counters[key]
    return stats


def run(args: argparse.Namespace) -> int:
    check_output(args.out_bag, args.overwrite, {'IN_BAG': args.in_bag})
    if args.detector == 'salad':
        return replay_camera.run(args)
    params = load_params_yaml(args.params) if args.params else DetectorParams()
    overrides = {k: v for k, v in (('detector', args.detector),
                                   ('checkpoint', args.checkpoint)) if v}
    params = dataclasses.replace(params, **overrides)
    stats = replay(args.in_bag, args.out_bag, params, args.points_topic, args.odom_topic,
                   progress=not args.quiet, overwrite=args.overwrite)
    alone = (f', {stats["without_odometry"]} without odometry (detected alone)'
             if stats.get('without_odometry') else '')
    if stats.get('bad_odometry'):
        alone += f', {stats["bad_odometry"]} bad odometry messages dropped'

    print(f'replayed {stats["sweeps"]} sweeps ({stats["dropped"]} dropped{alone}), '
          f'{stats["detections"]} detections -> {args.out_bag}')
    return 0
