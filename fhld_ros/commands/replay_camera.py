"""`fhld replay IN_BAG OUT_BAG --detector salad`: camera_lane_detector's pipeline over a bag's
camera images (what `fhld simulate --camera` writes: /camera/image_raw + /camera/camera_info;
a recorded bag's JPEG or PNG images on /camera/image_raw/compressed are read as well).

A thin driver of CameraPipeline, as the node is: every message in bag order, and after each one
the detection it made due, so a replay writes what the node publishes when each message is
handled before the next arrives (a live node busy with one image may see a newer one replace
the next: overtaken). OUT_BAG follows bagio's output rule, as the LiDAR replay's.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Iterator
from pathlib import Path

from tqdm import tqdm

from fhld_ros.bagio import BagWriter, check_output, read_messages, topic_counts
from fhld_ros.errors import ConfigError
from fhld_ros.lane_output import LANE_TOPICS, lane_messages
from fhld_ros.salad.camera_pipeline import CameraPipeline, distortion_notice, load_camera_detector
from fhld_ros.salad.parameters import CameraParams, load_camera_params_yaml
from msg_adapters.family import stamp_to_ns

IMAGE_TOPIC, CAMERA_INFO_TOPIC = '/camera/image_raw', '/camera/camera_info'


def replay_camera(in_bag: Path, out_bag: Path, params: CameraParams,
                  image_topic: str = IMAGE_TOPIC, camera_info_topic: str = CAMERA_INFO_TOPIC,
                  progress: bool = True, overwrite: bool = False) -> dict[str, int]:
    """Run the camera pipeline over in_bag and write its outputs to out_bag; returns counts."""
    inputs = {'IN_BAG': in_bag}
    check_output(out_bag, overwrite, inputs)  # before the model loads: fail fast
    counts = topic_counts(in_bag)
    image_topic = images_in(counts, image_topic, params.image_transport, progress)
    require_topics(in_bag, counts, (image_topic, camera_info_topic))
    pipeline = CameraPipeline(params, load_camera_detector(params))
    if pipeline.mount_warning:
        print(f'warning: {pipeline.mount_warning}', file=sys.stderr)
    lanes_topic = '/' + params.lanes_topic.strip('/')
    detections = 0
    with BagWriter(out_bag, overwrite, inputs) as writer:
        for _ in feed_camera(pipeline, in_bag, counts, image_topic, camera_info_topic,
                             'replay', progress):
            while (out := pipeline.detect()) is not None:
                for suffix, cdr in lane_messages(out).items():
                    writer.write(lanes_topic + suffix, LANE_TOPICS[suffix], out.stamp_ns, cdr)
                detections += 1
    c = pipeline.counters
    return {'images': c['images'] + c['bad_images'], 'dropped': c['bad_images'],
            'skipped': c['images_skipped'], 'bad_camera_info': c['bad_camera_info'],
            'detections': detections}


def feed_camera(pipeline: CameraPipeline, in_bag: Path, counts: dict[str, int],
                image_topic: str, camera_info_topic: str, desc: str, progress: bool
                ) -> Iterator[None]:
    """Every camera_info and image of in_bag into the pipeline in bag order, a dropped one
    written above the progress bar with its reason; yields after each message, for the
    caller to take what became due."""
    topics = [camera_info_topic, image_topic]
    bar = tqdm(total=sum(counts[t] for t in topics), unit='msg', disable=not progress,
               desc=desc, file=sys.stderr)
    said_distorted = False
    try:
        for topic, _, msg in read_messages(in_bag, topics):
            bar.update()
            if topic == camera_info_topic:
                problem = pipeline.receive_camera_info(msg)
                camera = pipeline.camera
                if problem is None and camera.lens is not None and not said_distorted:
                    said_distorted = True
                    text, level = distortion_notice(image_topic, camera_info_topic, camera.lens)
                    if level == 'warning':
                        bar.write(f'warning: {text}', file=sys.stderr)
            else:
                problem = pipeline.receive_image(msg).dropped
            if problem is not None:
                kind = 'camera_info' if topic == camera_info_topic else 'image'
                bar.write(f'dropped {kind} at {stamp_s(msg)}: {problem}')
            yield
    finally:
        bar.close()


def images_in(counts: dict[str, int], image_topic: str, transport: str, say: bool) -> str:
    """The topic a bag's images come from: image_topic, or its compressed one (image_transport's
    <image_topic>/compressed) where the parameters ask for it, or where the bag has only that
    (recorders often keep only the compressed images); said on stderr when `say`."""
    compressed = image_topic.rstrip('/') + '/compressed'
    if transport == 'compressed' or (not counts.get(image_topic) and counts.get(compressed)):
        if say and transport != 'compressed':
            print(f'images: {compressed} (the bag has no {image_topic})', file=sys.stderr)
        return compressed
    return image_topic


def require_topics(in_bag: Path, counts: dict[str, int], topics: tuple[str, ...]) -> None:
    """ConfigError naming the first of topics that in_bag (topic -> message count) lacks."""
    for topic in topics:
        if not counts.get(topic):
            missing = 'no messages on' if topic in counts else 'no topic'
            raise ConfigError(f'bag {in_bag} has {missing} {topic} (it has: '
                              f'{", ".join(sorted(counts)) or "nothing"})')


def stamp_s(msg: object) -> str:
    """A message's stamp for a warning (both replays): seconds, or that it is unreadable."""
    try:
        return f'{stamp_to_ns(msg.header.stamp) * 1e-9:.3f} s'
    except (AttributeError, TypeError, ValueError):
        return 'an unreadable stamp'


def run(args: argparse.Namespace) -> int:
    """`fhld replay --detector salad` (replay.py's arguments)."""
    params = load_camera_params_yaml(args.params) if args.params else CameraParams()
    if args.checkpoint:
        params = dataclasses.replace(params, checkpoint=args.checkpoint)
    stats = replay_camera(args.in_bag, args.out_bag, params, args.image_topic,
                          args.camera_info_topic, progress=not args.quiet,
                          overwrite=args.overwrite)
    bad_info = (f', {stats["bad_camera_info"]} bad camera_info messages'
                if stats['bad_camera_info'] else '')
    print(f'replayed {stats["images"]} images ({stats["dropped"]} dropped, {stats["skipped"]} '
          f'skipped by rate_hz{bad_info}), {stats["detections"]} detections -> {args.out_bag}')
    return 0
