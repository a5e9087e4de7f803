"""`fhld bench e2e`: sweep-to-/lanes latency of the running node over real DDS (loopback).

The node runs as its own process with its default parameters (the shipped FHLD weights); this
process publishes simulated 64x1024 Ouster-like sweeps and their odometry at 10 Hz on the wall
clock and timestamps every /lanes message on arrival. Latency = /lanes arrival - publish time
of the newest sweep it was computed from (the message's stamp). A sweep that never becomes the
newest sweep of a /lanes message counts as dropped. Backlog growth compares the median latency
of the last third of the run with the first third. The node's stage medians (node_stage_*_ms_p50,
from its /diagnostics) say where the time goes.
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
import time

import numpy as np

SECONDS = float(os.environ.get('FHLD_BENCH_E2E_SECONDS', '30'))
# node parameters for the run, e.g. FHLD_BENCH_E2E_PARAMS='model_threads:=2 detector:=classical'
PARAMS = os.environ.get('FHLD_BENCH_E2E_PARAMS', '').split()
DISTINCT_SWEEPS = 50  # simulated once, then replayed with fresh stamps
RATE_HZ = 10.0


def _sweeps(count: int) -> list:
    from fhld_ros.sim.simulator import Simulator
    sim = Simulator(seed=5, sweeps=count, sensor='os1-64', road='highway', speed=20.0)
    return [sim.sweep(k) for k in range(count)]


def marker_array_stamp_ns(raw: bytes) -> int:
    """Header stamp of the first marker of a CDR-serialised MarkerArray, without decoding it."""
    if len(raw) < 8 or raw[1] not in (0, 1):
        raise ValueError('not a CDR-serialised MarkerArray')
    order = '<' if raw[1] == 1 else '>'  # encapsulation: CDR little / big endian
    if struct.unpack_from(f'{order}I', raw, 4)[0] == 0 or len(raw) < 16:
        raise ValueError('MarkerArray without markers')
    sec, nanosec = struct.unpack_from(f'{order}iI', raw, 8)
    return sec * 1_000_000_000 + nanosec


def bench_e2e(seconds: float = SECONDS) -> dict[str, float]:
    from fhld_ros.ros.env import loopback_dds_env
    os.environ.update(loopback_dds_env())
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from msg_adapters.family import rclpy_family
    from msg_adapters.odometry import make_odometry
    from msg_adapters.pointcloud2 import create_cloud

    sweeps = _sweeps(DISTINCT_SWEEPS)
    ros_args = ['--ros-args', *[a for p in PARAMS for a in ('-p', p)]] if PARAMS else []
    node = subprocess.Popen([sys.executable, '-m', 'fhld_ros.ros.node', *ros_args],
                            env=dict(os.environ),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    family = rclpy_family()
    context = rclpy.Context()
    rclpy.init(context=context)
    bench = rclpy.create_node('fhld_bench_e2e', context=context)
    arrivals: list[tuple[int, float]] = []
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    # Raw bytes: deserialising every MarkerArray in Python held this process's GIL for ms and
    # delayed the next publish (measured: sweeps published right after a /lanes arrival took
    # 33 ms to reach the node, 9 ms otherwise).
    bench.create_subscription(family.cls('visualization_msgs/msg/MarkerArray'), 'lanes',
                              lambda raw: arrivals.append((marker_array_stamp_ns(raw),
                                                           time.monotonic())), reliable, raw=True)
    node_diag: dict[str, str] = {}
    bench.create_subscription(
        family.cls('diagnostic_msgs/msg/DiagnosticArray'), 'diagnostics',
        lambda m: node_diag.update({kv.key: kv.value for st in m.status for kv in st.values}),
        reliable)
    points = bench.create_publisher(family.cls('sensor_msgs/msg/PointCloud2'), 'points',
                                    reliable)
    odom = bench.create_publisher(family.cls('nav_msgs/msg/Odometry'), 'odom', reliable)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(bench)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    published: dict[int, float] = {}
    try:
        deadline = time.monotonic() + 60
        while points.get_subscription_count() == 0 or odom.get_subscription_count() == 0:
            if time.monotonic() > deadline or node.poll() is not None:
                raise RuntimeError('the lane_detector node did not come up')
            time.sleep(0.1)
        time.sleep(1.0)
        start_ns, period = 1_700_000_000_000_000_000, 1.0 / RATE_HZ
        cloud_cls = family.cls('sensor_msgs/msg/PointCloud2')
        count = int(seconds * RATE_HZ)
        t0 = time.monotonic()
        for k in range(count):
            sweep = sweeps[k % len(sweeps)]
            stamp = start_ns + k * 100_000_000
            header = family.header(stamp, 'lidar')
            cloud = create_cloud(cloud_cls, header, sweep.points, height=sweep.height)
            due = t0 + k * period
            time.sleep(max(0.0, due - time.monotonic()))
            odom.publish(make_odometry(family, family.header(stamp, 'odom'), 'lidar',
                                       sweep.sensor_to_odom))
            published[stamp] = time.monotonic()
            points.publish(cloud)
        time.sleep(1.5)
    finally:
        node.terminate()
        node.wait(timeout=20)
        executor.shutdown()
        spinner.join(timeout=10)
        bench.destroy_node()
        context.try_shutdown()
    latencies = np.array([(t - published[s]) * 1e3 for s, t in arrivals if s in published])
    if latencies.size < 3:
        raise RuntimeError(f'only {latencies.size} /lanes messages arrived')
    third = latencies.size // 3
    return {
        'e2e_latency_ms_p50': float(np.percentile(latencies, 50)),
        'e2e_latency_ms_p95': float(np.percentile(latencies, 95)),
        'e2e_latency_growth_ms': float(np.median(latencies[-third:])
                                       - np.median(latencies[:third])),
        'e2e_seconds': float(seconds), 'sweeps_published': float(len(published)),
        'lanes_messages': float(latencies.size),
        'sweeps_dropped': float(len(published) - len({s for s, _ in arrivals})),
        # the node's own view (its /diagnostics): stage medians from callback arrival
        **{f'node_{k}': float(v) for k, v in node_diag.items()
           if k.startswith(('stage_', 'latency_ms_'))},
    }
