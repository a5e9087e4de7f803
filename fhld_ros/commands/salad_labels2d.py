"""`fhld salad-labels2d IN_BAG OUT_DIR`: SALAD's lanes as 2D lane labels of a bag's camera
images, for `fhld autolabel` to lift with the drive's LiDAR sweeps: pseudo-labels, so a drive
nobody labelled by hand becomes LiDAR training data (`fhld autolabel --lane-map`).

SALAD draws the lines where the image shows them and misses their depth (docs/salad.md); the
lanes projected back into the image they came from are good 2D labels, and autolabel takes their
depth from the ground returns, not from SALAD. A high-precision rule decides which lanes become
labels: a lane scoring at least --min-score, cut to the image. A missed line costs a training
bag less than a false one, which it teaches as paint.

OUT_DIR gets `<stamp_ns>.json` per image (camera/labels2d.py), also for an image without lanes
(no label: autolabel then lifts nothing there). OUT_DIR must be new or empty;
--overwrite replaces only the files of this bag's stamps.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from fhld_ros.bagio import check_file_output, topic_counts
from fhld_ros.camera.labels2d import ImageLabels, LaneLabel2D, label_path, write_labels
from fhld_ros.commands.replay_camera import (
    CAMERA_INFO_TOPIC,
    IMAGE_TOPIC,
    feed_camera,
    require_topics,
)
from fhld_ros.errors import ConfigError
from fhld_ros.salad.camera_pipeline import CameraImage, CameraPipeline, load_camera_detector
from fhld_ros.salad.figure import project
from fhld_ros.salad.parameters import CameraParams

DEFAULT_MIN_SCORE = 0.8
MIN_LABEL_PX = 20.0  # a label spans at least this many pixels


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('in_bag', type=Path, help='bag with camera images and camera_info')
    parser.add_argument('out_dir', type=Path, help='folder for <stamp_ns>.json label files')
    parser.add_argument('--min-score', type=float, default=DEFAULT_MIN_SCORE,
                        help='a lane becomes a label from this score (SALAD mean cell '
                             f'probability; default {DEFAULT_MIN_SCORE})')
    parser.add_argument('--checkpoint', default='', help='SALAD weights (default: shipped)')
    parser.add_argument('--image-topic', default=IMAGE_TOPIC)
    parser.add_argument('--camera-info-topic', default=CAMERA_INFO_TOPIC)
    parser.add_argument('--overwrite', action='store_true',
                        help="replace label files of this bag's stamps in OUT_DIR")
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def image_labels(image: CameraImage, lanes: list[np.ndarray], scores: np.ndarray,
                 min_score: float) -> ImageLabels:
    """The lanes (optical frame) scoring >= min_score, projected with the image's own K and
    lens distortion and cut to the image, as its 2D labels."""
    width, height = image.camera.width, image.camera.height
    labels = []
    for lane, score in zip(lanes, scores):
        if score < min_score:
            continue
        uv = project(lane, image.camera.K, image.camera.lens)
        uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0)
                & (uv[:, 1] <= height - 1)]
        if len(uv) >= 2 and np.ptp(uv, axis=0).max() >= MIN_LABEL_PX:
            labels.append(LaneLabel2D(len(labels), uv))
    return ImageLabels(image.stamp_ns, image.frame_id, (width, height), labels)


def _check_out_dir(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f'OUT_DIR {out_dir}: exists and is not a directory')
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise ConfigError(f'OUT_DIR {out_dir}: not empty (--overwrite replaces the label files '
                          "of this bag's stamps, nothing else)")


def write_pseudo_labels(in_bag: Path, out_dir: Path, min_score: float = DEFAULT_MIN_SCORE,
                        checkpoint: str = '', image_topic: str = IMAGE_TOPIC,
                        camera_info_topic: str = CAMERA_INFO_TOPIC, overwrite: bool = False,
                        progress: bool = True) -> dict[str, int]:
    """Label every image of in_bag that has a usable camera_info; returns counts."""
    if not 0.0 <= min_score <= 1.0:
        raise ConfigError(f'--min-score must be within [0, 1], got {min_score:g}')
    _check_out_dir(out_dir, overwrite)
    counts = topic_counts(in_bag)
    require_topics(in_bag, counts, (image_topic, camera_info_topic))
    # every image is detected (rate_hz at its maximum); the lanes are taken from the detector
    # itself (optical frame, all scores), filtered here by min_score
    params = dataclasses.replace(CameraParams(), rate_hz=1000.0, checkpoint=checkpoint)
    pipeline = CameraPipeline(params, load_camera_detector(params))
    found = {'images': 0, 'labelled': 0, 'labels': 0}
    for _ in feed_camera(pipeline, in_bag, counts, image_topic, camera_info_topic,
                         'salad-labels2d', progress):
        image = pipeline.due_image()
        if image is None:
            continue
        labels = image_labels(image, *pipeline.detector(
            image.rgb, image.camera.K, distortion=image.camera.lens), min_score)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = label_path(out_dir, image.stamp_ns)
        check_file_output(path, overwrite, {'IN_BAG': in_bag}, 'OUT_DIR')
        write_labels(path, labels)
        found['images'] += 1
        found['labelled'] += bool(labels.lanes)
        found['labels'] += len(labels.lanes)
    return {**found, 'dropped': pipeline.counters['bad_images']}


def run(args: argparse.Namespace) -> int:
    found = write_pseudo_labels(args.in_bag, args.out_dir, args.min_score, args.checkpoint,
                                args.image_topic, args.camera_info_topic, args.overwrite,
                                progress=not args.quiet)
    print(f'{found["images"]} images ({found["dropped"]} dropped): {found["labels"]} lane '
          f'labels on {found["labelled"]} of them (score >= {args.min_score:g}) -> '
          f'{args.out_dir}')
    return 0
