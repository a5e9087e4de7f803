"""A user's stack as test_graph_e2e.py plays it: plain rclpy publishers in their own process.

    python test/graph_publisher.py --odom-hz 10 --sweeps 40   # /odom then /points, same stamps
    python test/graph_publisher.py --odom-hz 50 --sweeps 40   # odometry on its own stamps
    python test/graph_publisher.py --odom-hz 200 --best-effort --malformed 2   # a driver's QoS

Clouds are Ouster-like 64 x 1024 organised sweeps of 48-byte points (x, y, z, intensity, t,
reflectivity, ring, ambient, range; NaN no-returns), stamped on the sensor's own regular clock
(the wall clock at start + k / 10 s) and published at that moment. Odometry drives straight
ahead at 10 m/s. With --malformed N, N clouds whose data is shorter than their header says go
out midway between two sweeps. Prints one JSON line: the stamps (ns) of the good clouds
published. Imports nothing from fhld_ros.
"""
from __future__ import annotations

import argparse
import array
import json
import time

import numpy as np
import rclpy
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField

ROWS, COLS = 64, 1024
SWEEP_NS = 100_000_000
OUSTER = np.dtype({'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient',
                             'range'],
                   'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
                   'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32], 'itemsize': 48})
DATATYPES = {'<f4': PointField.FLOAT32, '<u4': PointField.UINT32, '<u2': PointField.UINT16}


def ouster_points(seed: int = 0) -> np.ndarray:
    """One sweep: rings on a flat road 1.8 m below the sensor, painted lines at +-1.8 m."""
    rng = np.random.default_rng(seed)
    elevation = np.deg2rad(np.linspace(-22.5, 22.5, ROWS))[:, None]
    azimuth = np.linspace(np.pi, -np.pi, COLS, endpoint=False)[None, :]
    with np.errstate(divide='ignore'):
        distance = np.where(elevation < -0.02, 1.8 / -np.tan(elevation), np.nan) + 0 * azimuth
    distance[rng.random(distance.shape) < 0.05] = np.nan  # dropouts
    distance[distance > 60] = np.nan
    points = np.zeros((ROWS, COLS), dtype=OUSTER)
    points['x'] = distance * np.cos(azimuth)
    points['y'] = distance * np.sin(azimuth)
    points['z'] = np.where(np.isnan(distance), np.nan, -1.8)
    paint = np.abs(np.abs(points['y']) - 1.8) < 0.08
    points['intensity'] = np.where(paint, 200.0, 20.0) + rng.uniform(0, 5, (ROWS, COLS))
    points['ring'] = np.arange(ROWS)[:, None]
    points['range'] = np.nan_to_num(distance * 1000).astype(np.uint32)
    return points.reshape(-1)


def cloud(stamp_ns: int, points: np.ndarray) -> PointCloud2:
    msg = PointCloud2(height=ROWS, width=COLS, point_step=OUSTER.itemsize,
                      row_step=OUSTER.itemsize * COLS, is_bigendian=False, is_dense=False)
    msg.header.frame_id = 'os_lidar'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.fields = [PointField(name=name, offset=OUSTER.fields[name][1], count=1,
                             datatype=DATATYPES[OUSTER.fields[name][0].str])
                  for name in OUSTER.names]
    msg.data = array.array('B', points.tobytes())
    return msg


def truncated(msg: PointCloud2) -> PointCloud2:
    """The same cloud with a row missing from its data: malformed."""
    msg.data = msg.data[:-msg.row_step]
    return msg


def odometry(stamp_ns: int, start_ns: int) -> Odometry:
    msg = Odometry(child_frame_id='os_lidar')
    msg.header.frame_id = 'odom'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.pose.pose.position.x = 10.0 * (stamp_ns - start_ns) * 1e-9
    msg.pose.pose.orientation.w = 1.0
    msg.twist.twist.linear.x = 10.0
    return msg


def sleep_until(wall_ns: int) -> None:
    delay = (wall_ns - time.time_ns()) * 1e-9
    if delay > 0:
        time.sleep(delay)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--odom-hz', type=int, default=10, help='10: the clouds\' stamps; '
                        'more: odometry on its own stamps, the clouds between them')
    parser.add_argument('--sweeps', type=int, default=40)
    parser.add_argument('--match-timeout', type=float, default=60.0)
    parser.add_argument('--best-effort', action='store_true',
                        help='best-effort publishers, as LiDAR drivers have')
    parser.add_argument('--malformed', type=int, default=0, help='malformed clouds midway')
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node('graph_publisher')
    reliability = (ReliabilityPolicy.BEST_EFFORT if args.best_effort
                   else ReliabilityPolicy.RELIABLE)
    points_pub = node.create_publisher(PointCloud2, 'points',
                                       QoSProfile(depth=10, reliability=reliability))
    odom_pub = node.create_publisher(Odometry, 'odom',
                                     QoSProfile(depth=50, reliability=reliability))
    deadline = time.monotonic() + args.match_timeout
    while (points_pub.get_subscription_count() < 1 or odom_pub.get_subscription_count() < 1):
        if time.monotonic() > deadline:
            raise SystemExit('graph_publisher: the node never subscribed')
        time.sleep(0.05)
    time.sleep(1.0)  # both sides of the match settled
    points = ouster_points()
    start = time.time_ns() + 200_000_000
    stamps = []
    # after which sweeps a malformed cloud follows, half a sweep later
    malformed = {args.sweeps // 2 + 2 * i for i in range(args.malformed)}
    if args.odom_hz == 10:  # /odom then /points with identical stamps
        for k in range(args.sweeps):
            stamp = start + k * SWEEP_NS
            sleep_until(stamp)
            odom_pub.publish(odometry(stamp, start))
            points_pub.publish(cloud(stamp, points))
            stamps.append(stamp)
            if k in malformed:
                sleep_until(stamp + SWEEP_NS // 2)
                points_pub.publish(truncated(cloud(stamp + SWEEP_NS // 2, points)))
    else:  # odometry every tick on its own stamps; a cloud half a tick after every n-th one
        tick = 1_000_000_000 // args.odom_hz
        per_sweep = SWEEP_NS // tick
        for j in range(args.sweeps * per_sweep + 2):
            stamp = start + j * tick
            sleep_until(stamp)
            odom_pub.publish(odometry(stamp, start))
            if j % per_sweep == 1 and len(stamps) < args.sweeps:
                sleep_until(stamp + tick // 2)
                points_pub.publish(cloud(stamp + tick // 2, points))
                stamps.append(stamp + tick // 2)
            elif j % per_sweep == per_sweep // 2 + 1 and len(stamps) - 1 in malformed:
                malformed.discard(len(stamps) - 1)
                points_pub.publish(truncated(cloud(stamp, points)))
    time.sleep(1.0)  # reliable delivery of the last messages
    print(json.dumps({'stamps': stamps}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
