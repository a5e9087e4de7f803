"""Latency of the node in a user's graph: test/graph_publisher.py -> lane_detector -> /lanes.

    python test/graph_latency.py --sweeps 300 --odom-hz 10   # docs/performance.md, issue #17
    python test/graph_latency.py --sweeps 300 --odom-hz 50
    python test/graph_latency.py --sweeps 300 --dds default   # Fast DDS's 512 kB segment
    python test/graph_latency.py --dds default --publisher-args '--best-effort' --log node.txt

Starts the node with its defaults (the shipped FHLD weights), runs the publisher in its own
process (plain rclpy, 64 x 1024 Ouster-like sweeps stamped and published on the wall clock) and
times each /lanes message against its cloud stamp. Prints one JSON line: sweeps, sweeps with
/lanes, p50 / p95 ms and the node's counters and stage medians. A measurement, not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import NodeOutputs, wait_until
from visualization_msgs.msg import MarkerArray

from fhld_ros.ros.env import loopback_dds_env
from msg_adapters.lanes import marker_array_to_lanes

PUBLISHER = Path(__file__).resolve().parent / 'graph_publisher.py'
DIAGNOSTICS = ('clouds', 'detections', 'bad_clouds', 'input_reliability', 'sweeps_skipped',
               'clouds_without_odometry', 'odometry_timeouts', 'clouds_lost_in_dds',
               'odometry_lost_in_dds', 'odometry', 'clouds_extrapolated',
               'stage_ingest_ms_p50', 'stage_wait_ms_p50',
               'stage_raster_ms_p50', 'stage_detect_ms_p50')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--sweeps', type=int, default=300)
    parser.add_argument('--odom-hz', type=int, default=10)
    parser.add_argument('--dds', choices=('project', 'default'), default='project')
    parser.add_argument('--params', nargs='*', default=[], help='node parameters, name:=value')
    parser.add_argument('--log', help='the node\'s output to this file')
    parser.add_argument('--publisher-args', default='',
                        help="more test/graph_publisher.py arguments, e.g. '--best-effort'")
    args = parser.parse_args()
    env = loopback_dds_env(dds=args.dds)
    os.environ.update(env)  # this process's listener joins the same loopback domain
    ros_args = ['--ros-args', *[a for p in args.params for a in ('-p', p)]] if args.params else []
    log = open(args.log, 'w') if args.log else subprocess.DEVNULL  # noqa: SIM115
    node = subprocess.Popen([sys.executable, '-m', 'fhld_ros.ros.lane_detector', *ros_args],
                            env=env, stdout=log, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(context=context)
    outputs = NodeOutputs(context, 'graph_latency')
    arrivals: dict[int, int] = {}
    outputs.node.create_subscription(
        MarkerArray, 'lanes', lambda msg: arrivals.setdefault(
            marker_array_to_lanes(msg).stamp_ns, time.time_ns()),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    try:
        if not wait_until(lambda: outputs.diagnostics, 90):
            raise SystemExit('the node never came up')
        done = subprocess.run([sys.executable, str(PUBLISHER), '--odom-hz', str(args.odom_hz),
                               '--sweeps', str(args.sweeps), *args.publisher_args.split()],
                              env=env, capture_output=True,
                              text=True, check=True)
        stamps = json.loads(done.stdout.strip().splitlines()[-1])['stamps']
        time.sleep(2.0)
        latency = [(arrivals[s] - s) / 1e6 for s in stamps if s in arrivals]
        values = outputs.diagnostic_values()
        print(json.dumps({'sweeps': len(stamps), 'with_lanes': len(latency),
                          'p50_ms': round(float(np.percentile(latency, 50)), 1),
                          'p95_ms': round(float(np.percentile(latency, 95)), 1),
                          **{k: values.get(k) for k in DIAGNOSTICS}}))
    finally:
        outputs.close()
        node.terminate()
        node.wait(timeout=20)
        context.try_shutdown()


if __name__ == '__main__':
    main()
