"""A user's camera driver as test_camera_graph.py plays it: plain rclpy publishers in their own
process.

    python test/camera_publisher.py --frames 20 --corrupt-after 5             # rgb8 Images
    python test/camera_publisher.py --frames 20 --corrupt-after 5 --jpeg      # JPEGs

Publishes /camera/camera_info and either /camera/image_raw (sensor_msgs/Image, rgb8: 1.5 MB a
message) or, with --jpeg, /camera/image_raw/compressed (sensor_msgs/CompressedImage, format
'rgb8; jpeg compressed bgr8' as image_transport's compressed plugin writes it) at --hz on the
wall clock: 960x540 images of a road with two white lines. With --corrupt-after N, one image
cut short half a frame after image N. Waits for a subscriber on both topics first. With
--latched-info, camera_info goes out once, at start, transient local (as a driver that latches
it): before any subscriber exists; then it waits for a transient-local reader of it. With
--go-on-stdin, the images start once a line comes on stdin as well (when the test's listener is
ready). Prints one JSON line: the stamps (ns) of the good images published. Imports nothing from
fhld_ros.
"""
from __future__ import annotations

import argparse
import array
import io
import json
import sys
import time

import rclpy
from graph_publisher import sleep_until  # this folder: the LiDAR driver's publisher
from PIL import Image as PilImage
from PIL import ImageDraw
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

WIDTH, HEIGHT, FOCAL = 960, 540, 685.0


def road() -> PilImage.Image:
    """Grey road below a sky, two white lines meeting at the horizon."""
    image = PilImage.new('RGB', (WIDTH, HEIGHT), (150, 170, 200))
    draw = ImageDraw.Draw(image)
    horizon = HEIGHT // 2
    draw.rectangle((0, horizon, WIDTH, HEIGHT), fill=(70, 70, 72))
    for bottom in (150, 810):
        draw.line((bottom, HEIGHT, WIDTH // 2 + (bottom - WIDTH // 2) // 30, horizon + 4),
                  fill=(235, 235, 230), width=9)
    return image


def camera_info(stamp_ns: int) -> CameraInfo:
    msg = CameraInfo(width=WIDTH, height=HEIGHT, distortion_model='plumb_bob')
    msg.header.frame_id = 'camera'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    cx, cy = (WIDTH - 1) / 2, (HEIGHT - 1) / 2
    msg.k = [FOCAL, 0.0, cx, 0.0, FOCAL, cy, 0.0, 0.0, 1.0]
    msg.p = [FOCAL, 0.0, cx, 0.0, 0.0, FOCAL, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.d = [0.0] * 5
    return msg


def image_message(stamp_ns: int, image: PilImage.Image, jpeg: bool) -> Image | CompressedImage:
    if jpeg:
        out = io.BytesIO()
        image.save(out, format='JPEG', quality=90)
        msg = CompressedImage(format='rgb8; jpeg compressed bgr8')
        msg.data = array.array('B', out.getvalue())
    else:
        msg = Image(height=HEIGHT, width=WIDTH, encoding='rgb8', step=3 * WIDTH)
        msg.data = array.array('B', image.tobytes())
    msg.header.frame_id = 'camera'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def cut_short(msg: Image | CompressedImage) -> Image | CompressedImage:
    msg.data = msg.data[:len(msg.data) // 3]
    return msg


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--frames', type=int, default=8)
    parser.add_argument('--hz', type=float, default=10.0)
    parser.add_argument('--corrupt-after', type=int, default=-1)
    parser.add_argument('--jpeg', action='store_true', help='CompressedImage JPEGs')
    parser.add_argument('--latched-info', action='store_true',
                        help='camera_info once, at start, transient local')
    parser.add_argument('--go-on-stdin', action='store_true',
                        help='the images wait for a line on stdin too')
    parser.add_argument('--match-timeout', type=float, default=60.0)
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node('camera_publisher')
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    info_pub = node.create_publisher(CameraInfo, 'camera/camera_info',
                                     latched if args.latched_info else qos)
    if args.latched_info:
        info_pub.publish(camera_info(time.time_ns()))
    image_pub = (node.create_publisher(CompressedImage, 'camera/image_raw/compressed', qos)
                 if args.jpeg else node.create_publisher(Image, 'camera/image_raw', qos))
    deadline = time.monotonic() + args.match_timeout
    while info_pub.get_subscription_count() < 1 or image_pub.get_subscription_count() < 1 or (
            args.latched_info and not any(
                info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                for info in node.get_subscriptions_info_by_topic('/camera/camera_info'))):
        if time.monotonic() > deadline:
            raise SystemExit('camera_publisher: the node never subscribed')
        time.sleep(0.05)
    time.sleep(1.0)  # both sides of the match settled
    if args.go_on_stdin:
        sys.stdin.readline()
    image = road()
    period = int(1e9 / args.hz)
    start = time.time_ns() + 200_000_000
    if not args.latched_info:
        info_pub.publish(camera_info(start - period))  # the intrinsics before the first image
    stamps = []
    for k in range(args.frames):
        stamp = start + k * period
        sleep_until(stamp)
        if not args.latched_info:
            info_pub.publish(camera_info(stamp))
        image_pub.publish(image_message(stamp, image, args.jpeg))
        stamps.append(stamp)
        if k == args.corrupt_after:
            sleep_until(stamp + period // 2)
            image_pub.publish(cut_short(image_message(stamp + period // 2, image, args.jpeg)))
    time.sleep(0.5)  # reliable: the last messages delivered before the writer goes
    print(json.dumps({'stamps': stamps}))
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
