"""`fhld import SRC OUT_BAG`: PCD files or KITTI `.bin` sweeps into an MCAP bag for replay.

SRC is one file or a folder of them (every .pcd or every .bin directly in it, in natural name
order: 2.pcd before 10.pcd; a folder mixing both kinds is refused, since their order and
intensity units would be a guess). The bag has /points (sensor_msgs/PointCloud2: float32 x, y,
z, intensity in the file's own units, organised when the PCD is) and, with --poses, /odom
(nav_msgs/Odometry: the sensor's pose, header.frame_id --odom-frame, child_frame_id the cloud
frame, stamped like its sweep), so `fhld replay` needs no extrinsic. With --images and --calib
it also holds the camera, as `fhld simulate --camera` writes it for `fhld autolabel`: one image
per sweep (natural name order) on /camera/image_raw and /camera/camera_info at the sweep's
stamp, and the calibration's extrinsic on /tf_static. OUT_BAG follows bagio's output rule
(refused when it exists without --overwrite, is not a bag, or overlaps an input).
"""
from __future__ import annotations

import argparse
import re
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fhld_ros.bagio import BagWriter, check_output
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.camera_topics import write_camera
from fhld_ros.errors import ConfigError
from fhld_ros.importing import kitti
from fhld_ros.importing.pcd import IDENTITY_VIEWPOINT, read_pcd, to_xyzi
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

KINDS = {'.pcd': 'PCD', '.bin': 'KITTI .bin'}
IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg')
DEFAULT_START_S = '1700000000'  # a plausible wall-clock time, as `fhld simulate` uses


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('src', type=Path, metavar='SRC',
                        help='a .pcd or KITTI .bin file, or a folder of them')
    parser.add_argument('out_bag', type=Path, metavar='OUT_BAG', help='bag directory to write')
    parser.add_argument('--frame-id', default='lidar', help='cloud frame (default lidar)')
    timing = parser.add_mutually_exclusive_group()
    timing.add_argument('--rate', type=float, default=10.0,
                        help='sweeps per second for the stamps (default 10)')
    timing.add_argument('--times', type=Path, metavar='FILE',
                        help='KITTI times.txt: seconds per sweep from --start (instead of --rate)')
    parser.add_argument('--start', default=DEFAULT_START_S, metavar='SECONDS',
                        help=f'stamp of the first sweep (default {DEFAULT_START_S})')
    parser.add_argument('--poses', type=Path, metavar='FILE',
                        help='one 3x4 row-major sensor -> odom transform per line and sweep '
                        '(KITTI odometry layout); writes /odom')
    parser.add_argument('--kitti-calib', type=Path, metavar='FILE',
                        help='KITTI calib.txt: --poses are KITTI camera-0 poses; converted to '
                        'LiDAR poses with its Tr (velodyne -> camera)')
    parser.add_argument('--odom-frame', default='odom', help='/odom header frame (default odom)')
    parser.add_argument('--images', type=Path, metavar='SRC',
                        help='camera images (.png/.jpg file or folder), one per sweep in name '
                        'order; needs --calib')
    parser.add_argument('--calib', type=Path, metavar='YAML',
                        help='camera calibration of --images (docs/annotation.md)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing OUT_BAG (only a rosbag2 bag folder)')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def _natural_key(path: Path) -> list:
    return [(0, int(part), '') if part.isdigit() else (1, 0, part)
            for part in re.split(r'(\d+)', path.name) if part]


def collect_sources(src: Path) -> tuple[list[Path], str]:
    """The files to import in order and their kind ('.pcd' or '.bin')."""
    if src.is_file():
        suffix = src.suffix.lower()
        if suffix not in KINDS:
            raise ConfigError(f'{src} is neither a .pcd nor a KITTI .bin file')
        return [src], suffix
    if not src.is_dir():
        raise ConfigError(f'{src} does not exist')
    found = {s: sorted((p for p in src.iterdir() if p.is_file() and p.suffix.lower() == s),
                       key=_natural_key) for s in KINDS}
    if found['.pcd'] and found['.bin']:
        raise ConfigError(f'{src} mixes {len(found[".pcd"])} .pcd and {len(found[".bin"])} .bin '
                          'files: import each kind into its own bag')
    suffix = '.pcd' if found['.pcd'] else '.bin'
    if not found[suffix]:
        raise ConfigError(f'{src} has no .pcd or .bin files')
    return found[suffix], suffix


def sweep_stamps(count: int, args: argparse.Namespace) -> np.ndarray:
    """int64 nanosecond stamps: --start plus --times, or one sweep every 1 / --rate."""
    try:
        start_ns = int(Decimal(args.start) * 1_000_000_000)
    except (ArithmeticError, ValueError):
        raise ConfigError(f'--start must be a number of seconds, got {args.start!r}') from None
    if start_ns <= 0:
        raise ConfigError(f'--start must be > 0 (ROS time 0 means "unset"), got {args.start}')
    if args.times is not None:
        offsets = kitti.read_times(args.times)
        if len(offsets) != count:
            raise ConfigError(f'{args.times} has {len(offsets)} times for {count} sweeps')
        if offsets[0] < 0:
            raise ConfigError(f'{args.times}: times must be >= 0, the first is {offsets[0]:g}')
        return start_ns + np.round(offsets * 1e9).astype(np.int64)
    if not 0.0 < args.rate <= 1000.0:
        raise ConfigError(f'--rate must be within (0, 1000] Hz, got {args.rate:g}')
    return start_ns + np.round(np.arange(count) * (1e9 / args.rate)).astype(np.int64)


def sensor_poses(count: int, args: argparse.Namespace) -> np.ndarray | None:
    """(count, 4, 4) sensor -> odom transforms from --poses (None without)."""
    if args.poses is None:
        if args.kitti_calib is not None:
            raise ConfigError('--kitti-calib converts --poses: give --poses too')
        return None
    poses = kitti.read_poses(args.poses)
    if len(poses) != count:
        raise ConfigError(f'{args.poses} has {len(poses)} poses for {count} sweeps')
    if args.kitti_calib is not None:
        poses = kitti.camera_poses_to_lidar(poses, kitti.read_velo_to_cam(args.kitti_calib))
    return poses


def collect_images(args: argparse.Namespace, count: int) -> list[Path]:
    """The --images files in natural name order, one per sweep ([] without --images)."""
    if (args.images is None) != (args.calib is None):
        raise ConfigError('--images and --calib go together: the images need their calibration')
    if args.images is None:
        return []
    src = args.images
    files = [src] if src.is_file() else sorted(
        (p for p in src.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=_natural_key) if src.is_dir() else None
    if files is None:
        raise ConfigError(f'--images {src} does not exist')
    if len(files) != count:
        raise ConfigError(f'--images {src} has {len(files)} images for {count} sweeps')
    return files


def read_image(path: Path, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file that must be width x height."""
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as image:
            rgb = np.asarray(image.convert('RGB'))
    except (OSError, UnidentifiedImageError) as exc:
        raise ConfigError(f'--images {path}: cannot read it ({exc})') from exc
    if rgb.shape[:2] != (height, width):
        raise ConfigError(f'--images {path} is {rgb.shape[1]}x{rgb.shape[0]}, the calibration '
                          f'says {width}x{height}')
    return rgb


def _check_frames(args: argparse.Namespace) -> None:
    for option, name in (('--frame-id', args.frame_id), ('--odom-frame', args.odom_frame)):
        if not name or any(c.isspace() for c in name):
            raise ConfigError(f'{option} must be a non-empty name without spaces, got {name!r}')
    if args.frame_id == args.odom_frame:
        raise ConfigError(f'--frame-id and --odom-frame must differ, both are {args.frame_id!r}')


def read_sweep(path: Path, suffix: str) -> tuple[np.ndarray, int, bool]:
    """float32 x, y, z, intensity points of one file, its row count (organised PCD) and
    whether its PCD VIEWPOINT is not the identity."""
    if suffix == '.bin':
        return kitti.read_bin(path), 1, False
    cloud = read_pcd(path)
    moved = not np.allclose(cloud.viewpoint, IDENTITY_VIEWPOINT)
    return to_xyzi(cloud, path), cloud.height, moved


def run(args: argparse.Namespace) -> int:
    _check_frames(args)
    files, suffix = collect_sources(args.src)
    inputs = {'SRC': args.src, '--poses': args.poses, '--times': args.times,
              '--kitti-calib': args.kitti_calib, '--images': args.images, '--calib': args.calib}
    check_output(args.out_bag, args.overwrite, inputs)
    stamps = sweep_stamps(len(files), args)
    poses = sensor_poses(len(files), args)
    images = collect_images(args, len(files))
    calib = CameraCalibration.from_yaml(args.calib) if images else None
    points_total, moved = 0, 0
    with BagWriter(args.out_bag, args.overwrite, inputs) as bag:
        family = bag.family
        cloud_cls = family.cls('sensor_msgs/msg/PointCloud2')
        for k, path in enumerate(tqdm(files, unit='sweep', desc='import', file=sys.stderr,
                                      disable=args.quiet)):
            points, height, viewpoint_set = read_sweep(path, suffix)
            moved += viewpoint_set
            stamp = int(stamps[k])
            if poses is not None:  # before its sweep, so the sweep never waits for its pose
                bag.write('/odom', 'nav_msgs/msg/Odometry', stamp,
                          make_odometry(family, family.header(stamp, args.odom_frame),
                                        args.frame_id, poses[k]))
            bag.write('/points', 'sensor_msgs/msg/PointCloud2', stamp,
                      create_cloud(cloud_cls, family.header(stamp, args.frame_id), points,
                                   height=height))
            if calib is not None:
                write_camera(bag, calib, args.frame_id, stamp,
                             read_image(images[k], calib.width, calib.height), first=k == 0)
            points_total += len(points)
    if moved:  # points stay in the file's frame; the viewpoint is no pose the node can use
        print(f'note: {moved} file(s) have a non-identity VIEWPOINT, which is not applied',
              file=sys.stderr)
    odom = (' and /odom' if poses is not None else '') + (' and the camera' if images else '')
    print(f'imported {len(files)} {KINDS[suffix]} sweeps ({points_total} points) to /points'
          f'{odom} -> {args.out_bag}')
    return 0
