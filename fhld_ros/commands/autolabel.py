"""`fhld autolabel IN_BAG OUT_BAG --labels2d DIR`: 3D lane labels from 2D image labels and the
drive's LiDAR sweeps (ONCE-3DLanes section 3.2; fhld_ros/annotation, docs/annotation.md).

IN_BAG holds /points, optionally /odom (sweeps are then accumulated), and the camera: its
calibration from /camera/camera_info + /tf_static, or --calib YAML, and its image stamps from
/camera/camera_info or /camera/image_raw (without either, labels are matched to /points
stamps). Each label file (`<stamp_ns>.json`) labels the image at that stamp. OUT_BAG gets one
/lanes message (the /lanes contract: odometry frame, else the cloud frame) per labelled image,
its bev_window the ground the camera sees up to the depth its ground returns reach
(annotation/footprint.py), so `fhld eval OUT_BAG IN_BAG` scores it against the /lanes_gt lines
the camera could label. --once-json DIR also writes the ONCE-3DLanes layout (lanes in the
camera frame) per image; --once-dataset ROOT a SALAD training set in that layout, each
labelled image with its lanes (`fhld salad-train --once ROOT`). --lane-map makes OUT_BAG a
training bag as well (data/bag_source.py): the drive's /points and /odom copied, and on
/lanes_gt one message, stamped with the earliest sweep, holding the lane map of all images
(annotation/lane_map.py). OUT_BAG and the files follow bagio's output rule.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from fhld_ros.annotation.autolabel import Autolabeler, LabelledImage, PoseTrack
from fhld_ros.annotation.figure import draw_autolabel
from fhld_ros.annotation.lane_map import build_lane_map
from fhld_ros.bagio import (
    BagWriter,
    check_file_output,
    check_output,
    read_messages,
    topic_counts,
    write_file_atomically,
)
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.camera_topics import CAMERA_INFO, IMAGE, TF_STATIC
from fhld_ros.camera.labels2d import ImageLabels, read_label_dir
from fhld_ros.data.bag_source import LANES_GT, MARKER_ARRAY, ODOM, POINTS, TOPIC_TYPES
from fhld_ros.errors import ConfigError
from fhld_ros.salad.once_format import CAMERA, IMAGE_DIRS, write_once
from fhld_ros.salad.sample import CameraLaneSample
from msg_adapters.camera import msg_to_image
from msg_adapters.family import stamp_to_ns
from msg_adapters.lanes import lanes_to_marker_array, unique_marker_ids
from msg_adapters.odometry import odometry_to_matrix
from msg_adapters.pointcloud2 import read_xyzi


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('in_bag', type=Path, metavar='IN_BAG',
                        help='bag with /points (+ /odom) and the camera (or --calib)')
    parser.add_argument('out_bag', type=Path, metavar='OUT_BAG', help='bag to write /lanes to')
    parser.add_argument('--labels2d', type=Path, required=True, metavar='DIR',
                        help='2D lane labels, one <stamp_ns>.json per image')
    parser.add_argument('--calib', type=Path, metavar='YAML',
                        help='camera calibration (instead of /camera/camera_info + /tf_static)')
    parser.add_argument('--once-json', type=Path, metavar='DIR',
                        help='also write ONCE-3DLanes JSON (camera frame), one per image')
    parser.add_argument('--once-dataset', type=Path, metavar='ROOT',
                        help='also write each labelled image and its 3D lanes as ONCE-3DLanes '
                        'training data: ROOT/train/<IN_BAG name>/cam01/<stamp_ns>.json and '
                        'ROOT/data/.../<stamp_ns>.jpg (fhld salad-train --once ROOT)')
    parser.add_argument('--lane-map', action='store_true',
                        help='also make OUT_BAG a training bag (fhld train data.bags): /points '
                        'and /odom copied, the merged lanes of all images on /lanes_gt; needs '
                        'odometry')
    parser.add_argument('--plots', type=Path, metavar='DIR',
                        help='also draw each labelled image: lanes over the image and from above')
    parser.add_argument('--points-topic', default='/points')
    parser.add_argument('--odom-topic', default='/odom',
                        help="odometry topic; '' or a topic absent from the bag: per sweep")
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing OUT_BAG (only a bag folder) and the JSON files '
                        'it would write in --once-json')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def _read_camera_and_odometry(args: argparse.Namespace, counts: dict[str, int],
                              cloud_frame: str
                              ) -> tuple[CameraCalibration, list[int], PoseTrack | None]:
    """The calibration, the image stamps and the odometry, in one pass over the small topics
    (each pass decompresses the bag's chunks, images and clouds included)."""
    if args.calib is None and CAMERA_INFO not in counts:
        raise ConfigError(f'bag {args.in_bag} has no {CAMERA_INFO}; give the camera with '
                          '--calib YAML')
    odom = args.odom_topic if args.odom_topic and counts.get(args.odom_topic) else None
    # image stamps from the camera info, else the images, else the sweeps
    stamp_topic = next(t for t in (CAMERA_INFO, IMAGE, args.points_topic) if counts.get(t))
    topics = {stamp_topic, *(t for t in (CAMERA_INFO, TF_STATIC, odom) if t in counts)}
    infos, tf, stamps, poses, pose_stamps, odom_frame = [], [], [], [], [], None
    for topic, _, msg in read_messages(args.in_bag, sorted(topics)):
        if topic == stamp_topic:
            stamps.append(stamp_to_ns(msg.header.stamp))
        if topic == CAMERA_INFO:
            infos.append(msg)
        elif topic == TF_STATIC:
            tf.append(msg)
        elif topic == odom:
            if msg.child_frame_id != cloud_frame:
                raise ConfigError(f'{odom} gives the pose of "{msg.child_frame_id}", the clouds '
                                  f'are in "{cloud_frame}": autolabel needs the LiDAR\'s own '
                                  'odometry')
            try:
                poses.append(odometry_to_matrix(msg))
            except ValueError as exc:
                raise ConfigError(f'{odom}: {exc}') from exc
            pose_stamps.append(stamp_to_ns(msg.header.stamp))
            odom_frame = msg.header.frame_id
    calib = CameraCalibration.from_yaml(args.calib) if args.calib is not None else \
        CameraCalibration.from_messages(infos[0], tf, cloud_frame)
    track = None if odom is None else PoseTrack(np.array(pose_stamps, dtype=np.int64),
                                                np.stack(poses), str(odom_frame))
    return calib, stamps, track


def _check(args: argparse.Namespace) -> dict[str, int]:
    inputs = {'IN_BAG': args.in_bag, '--labels2d': args.labels2d}
    check_output(args.out_bag, args.overwrite, inputs)
    counts = topic_counts(args.in_bag)
    if not counts.get(args.points_topic):
        raise ConfigError(f'bag {args.in_bag} has no messages on {args.points_topic} (it has: '
                          f'{", ".join(sorted(counts)) or "nothing"})')
    return counts


def _camera_lanes(image: LabelledImage) -> list[np.ndarray]:
    """The image's 3D lanes in the camera (optical) frame, to the 0.1 mm."""
    T = np.linalg.inv(image.T_out_camera)
    return [np.round(lane @ T[:3, :3].T + T[:3, 3], 4) for lane in image.lanes]


def _once_json(calib: CameraCalibration, image: LabelledImage) -> dict:
    """ONCE-3DLanes layout: lanes as [x, y, z] lists in the camera frame, K as a 3x4."""
    K = np.hstack([calib.K, np.zeros((3, 1))])
    return {'lanes': [lane.tolist() for lane in _camera_lanes(image)],
            'calibration': K.tolist(), 'stamp_ns': image.stamp_ns}


def _once_sequence(args: argparse.Namespace) -> str:
    """--once-dataset's sequence folder: IN_BAG's name."""
    return re.sub(r'\s', '_', args.in_bag.resolve().name)


def _check_inputs(args: argparse.Namespace, labels: dict[int, ImageLabels],
                  calib: CameraCalibration, poses: PoseTrack | None) -> None:
    """Labels for the camera's image size; poses for --lane-map."""
    for stamp, image in labels.items():
        if tuple(image.image_size) != (calib.width, calib.height):
            raise ConfigError(f'--labels2d {stamp}.json is for a {image.image_size[0]}x'
                              f'{image.image_size[1]} image, the camera is {calib.width}x'
                              f'{calib.height}')
    if args.lane_map and poses is None:
        where = f'no messages on {args.odom_topic}' if args.odom_topic else "--odom-topic ''"
        raise ConfigError(f'--lane-map needs the drive\'s poses, but {args.in_bag} has no '
                          f'odometry ({where})')


def _check_file_outputs(args: argparse.Namespace, labels: dict[int, ImageLabels]) -> None:
    """--once-json, --plots, --once-dataset: the files of the labels' stamps must be new or
    replaceable."""
    dataset = [] if args.once_dataset is None else [
        (args.once_dataset / split / _once_sequence(args) / CAMERA, suffix, '--once-dataset')
        for split, suffix in (('train', 'json'), (IMAGE_DIRS[0], 'jpg'))]
    for out_dir, suffix, option in ((args.once_json, 'json', '--once-json'),
                                    (args.plots, 'png', '--plots'), *dataset):
        if out_dir is None:
            continue
        if out_dir.exists() and not out_dir.is_dir():
            raise ConfigError(f'{option} {out_dir}: exists and is not a directory')
        if out_dir.is_dir():  # a new one cannot hold a conflict
            for stamp in labels:
                check_file_output(out_dir / f'{stamp}.{suffix}', args.overwrite,
                                  {'IN_BAG': args.in_bag}, option)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    counts = _check(args)
    labels = read_label_dir(args.labels2d)
    first_cloud = next(msg for _, _, msg in read_messages(args.in_bag, [args.points_topic]))
    cloud_frame = str(first_cloud.header.frame_id)
    calib, image_stamps, poses = _read_camera_and_odometry(args, counts, cloud_frame)
    _check_inputs(args, labels, calib, poses)
    labeler = Autolabeler(calib, labels, image_stamps, poses)
    if not labeler.stamps:
        raise ConfigError(f'no label file names an image of {args.in_bag}: label stamps '
                          f'{min(labels)}..{max(labels)} ns, images {min(image_stamps)}..'
                          f'{max(image_stamps)} ns')
    _check_file_outputs(args, labels)
    if args.once_dataset is not None and not counts.get(IMAGE):
        raise ConfigError(f'--once-dataset needs the images: {args.in_bag} has no {IMAGE}')
    images = {}  # rgb of labelled images waiting to be drawn or written
    wanted = set(labeler.stamps) if args.plots or args.once_dataset else set()
    unwritten = 0  # --once-dataset: labelled images whose image message was missing
    topics = [args.points_topic] + ([IMAGE] if wanted and counts.get(IMAGE) else []) + \
        ([args.odom_topic] if args.lane_map else [])
    bar = tqdm(total=counts[args.points_topic], unit='sweep', desc='autolabel',
               disable=args.quiet)
    with BagWriter(args.out_bag, overwrite=args.overwrite) as bag:
        fam = bag.family
        lane_map = _LaneMapWriter(bag, poses.frame_id) if args.lane_map else None

        def write(image: LabelledImage) -> None:
            nonlocal unwritten
            if lane_map is not None:
                lane_map.add(image)
            header = fam.header(image.stamp_ns, image.frame_id)
            bag.write('/lanes', 'visualization_msgs/msg/MarkerArray', image.stamp_ns,
                      lanes_to_marker_array(fam, header, image.lanes, np.ones(len(image.lanes)),
                                            unique_marker_ids(image.ids), image.outline))
            unwritten += not _write_files(args, calib, image, images.pop(image.stamp_ns, None))

        for topic, log_ns, msg in read_messages(args.in_bag, topics):
            if lane_map is not None and topic != IMAGE:
                lane_map.copy(POINTS if topic == args.points_topic else ODOM, log_ns, msg)
                if topic != args.points_topic:
                    continue
            if topic == IMAGE:
                if stamp_to_ns(msg.header.stamp) in wanted:
                    images[stamp_to_ns(msg.header.stamp)] = msg_to_image(msg)
                continue
            try:
                xyz, intensity = read_xyzi(msg)
            except ValueError as exc:
                raise ConfigError(f'{args.points_topic}: {exc}') from exc
            for image in labeler.add_sweep(stamp_to_ns(msg.header.stamp),
                                           str(msg.header.frame_id), xyz, intensity):
                write(image)
            bar.update()
        for image in labeler.finish():
            write(image)
        bar.close()
        if lane_map is not None:
            lane_map.finish()
        c = labeler.counts
        skipped = (f'skipped: {c.labels_without_image} label files without an image, '
                   f'{c.images_without_labels} images without labels, '
                   f'{c.images_without_points} images without LiDAR ground in view; '
                   f'{c.label_points_outside_image} label points outside the image dropped')
        if c.images == 0:  # inside the writer: the bag is not kept
            raise ConfigError(f'no image could be labelled in 3D ({skipped})')
    made = '' if lane_map is None else f', lane map of {lane_map.lines} lines'
    if unwritten:
        made += f'; {unwritten} labelled images not in --once-dataset (no image message)'
    print(f'fhld autolabel: {c.images} images labelled in 3D, {c.lanes} lanes{made}, '
          f'{time.perf_counter() - start:.1f} s; {skipped}', file=sys.stderr)
    return 0


def _write_files(args: argparse.Namespace, calib: CameraCalibration, image: LabelledImage,
                 rgb: np.ndarray | None) -> bool:
    """One labelled image's --once-json, --plots and --once-dataset files (each folder made
    with its first file: a failed run leaves none); False when --once-dataset lacks its image
    (rgb None: no image message at its stamp)."""
    if args.once_json is not None:
        args.once_json.mkdir(parents=True, exist_ok=True)
        (args.once_json / f'{image.stamp_ns}.json').write_text(
            json.dumps(_once_json(calib, image)) + '\n')
    if args.plots is not None:
        args.plots.mkdir(parents=True, exist_ok=True)
        _plot(args.plots / f'{image.stamp_ns}.png', calib, image, rgb)
    if args.once_dataset is None:
        return True
    if rgb is None:
        return False
    name = f'{_once_sequence(args)}/{CAMERA}/{image.stamp_ns}'
    write_once(args.once_dataset, 'train', [CameraLaneSample(rgb, calib.K, _camera_lanes(image),
                                                             name)])
    return True


class _LaneMapWriter:
    """--lane-map: the sweeps and odometry copied under the topics bag_source reads, and the
    lane map of all labelled images on /lanes_gt, stamped with the earliest sweep so that every
    training window (the newest /lanes_gt at or before its stamp) gets it."""

    def __init__(self, bag: BagWriter, frame_id: str) -> None:
        self.bag, self.frame_id = bag, frame_id
        self.lanes: list[np.ndarray] = []
        self.ids: list[int] = []
        self.images: list[int] = []  # the image of each lane: its lanes are distinct lines
        self.n_images = 0
        self.origins: list[np.ndarray] = []  # the camera's (x, y): near points weigh more
        self.first_sweep_ns: int | None = None
        self.lines = 0

    def copy(self, topic: str, log_ns: int, msg: Any) -> None:
        if topic == POINTS:
            stamp = stamp_to_ns(msg.header.stamp)
            self.first_sweep_ns = min(stamp, self.first_sweep_ns or stamp)
        self.bag.write(topic, TOPIC_TYPES[topic], log_ns, msg)

    def add(self, image: LabelledImage) -> None:
        self.images += [self.n_images] * len(image.lanes)
        self.n_images += 1
        self.origins += [image.T_out_camera[:2, 3]] * len(image.lanes)
        self.lanes += image.lanes
        self.ids += image.ids

    def finish(self) -> None:
        lines = build_lane_map(self.lanes, self.ids, self.images, self.origins)
        fam, stamp = self.bag.family, int(self.first_sweep_ns or 0)
        self.bag.write(LANES_GT, MARKER_ARRAY, stamp, lanes_to_marker_array(
            fam, fam.header(stamp, self.frame_id), [line.points for line in lines],
            np.ones(len(lines)), unique_marker_ids([line.label_id for line in lines])))
        self.lines = len(lines)


def _plot(path: Path, calib: CameraCalibration, image: LabelledImage,
          rgb: np.ndarray | None) -> None:
    T = np.linalg.inv(image.T_out_camera)
    to_camera = lambda xyz: xyz @ T[:3, :3].T + T[:3, 3]  # noqa: E731
    title = (f'fhld autolabel: image at {image.stamp_ns / 1e9:.3f} s, '
             f'{len(image.labels.lanes)} labels -> {len(image.lanes)} 3D lanes')
    write_file_atomically(path, lambda tmp: draw_autolabel(
        tmp, calib, image.labels, rgb, [to_camera(lane) for lane in image.lanes], image.ids,
        to_camera(image.ground), image.ground_contrast, title))
