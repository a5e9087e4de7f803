"""`fhld bench e2e`: sweep-to-/lanes latency of the running node over real DDS (loopback).

The node runs as its own process with its default parameters (the shipped FHLD weights); a
bench process publishes simulated 64x1024 Ouster-like sweeps and their odometry at 10 Hz on the
wall clock and timestamps every /lanes message on arrival. Latency = /lanes arrival - publish
time of the newest sweep it was computed from (the message's stamp). A sweep that never becomes
the newest sweep of a /lanes message counts as dropped. Backlog growth compares the median
latency of the last third of the run with the first third, and so does the node's resident
memory (sampled once a second). The node's stage medians (node_stage_*_ms_p50, from its
/diagnostics) say where the time goes, its counters (node_clouds_lost_in_dds, ...) what it lost.

Fast DDS reads its XML profile once per process, so each transport (`dds`: 'project' =
config/fastdds_loopback.xml, 'default' = Fast DDS's default 512 kB shared-memory segment, where
a 3 MB cloud travels in fragments; fhld_ros/ros/env.py) has its own bench process, ``python -m
fhld_ros.commands.bench_e2e --dds NAME``, which prints its summary as one JSON line last;
bench_e2e names the keys by transport: e2e_latency_ms_p50 -> e2e_project_latency_ms_p50,
sweeps_dropped -> e2e_default_sweeps_dropped.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fhld_ros.ros.env import PROFILES, loopback_dds_env
from fhld_ros.sim.simulator import Simulator, Sweep
from msg_adapters.family import rclpy_family
from msg_adapters.lanes import marker_array_stamp_ns
from msg_adapters.odometry import make_odometry
from msg_adapters.pointcloud2 import create_cloud

SECONDS = float(os.environ.get('FHLD_BENCH_E2E_SECONDS', '30'))
# node parameters for the run, e.g. FHLD_BENCH_E2E_PARAMS='model_threads:=2 detector:=classical'
PARAMS = os.environ.get('FHLD_BENCH_E2E_PARAMS', '').split()
DISTINCT_SWEEPS = 50  # simulated once, then replayed with fresh stamps
RATE_HZ = 10.0
START_NS = 1_700_000_000_000_000_000  # stamp of the first sweep
NODE_START_TIMEOUT_SEC = 60.0
CHILD_SLACK_SEC = 240.0  # a transport's child beyond its seconds: imports, node start, shutdown
# the node's own counters (/diagnostics) reported as node_<name>, 0.0 when it has none yet
NODE_COUNTERS = ('clouds_without_odometry', 'odometry_timeouts', 'clouds_lost_in_dds',
                 'odometry_lost_in_dds', 'sweeps_skipped')


def _sweeps(count: int) -> list[Sweep]:
    sim = Simulator(seed=5, sweeps=count, sensor='os1-64', road='highway', speed=20.0)
    return [sim.sweep(k) for k in range(count)]


class LanesClient:
    """A bench's side of a node under test (its own process): times /lanes arrivals and keeps
    the node's newest /diagnostics values. Add publishers to `node`, then start()."""

    def __init__(self, context: rclpy.Context, name: str) -> None:
        self.family = family = rclpy_family()
        self.node = rclpy.create_node(name, context=context)
        self.arrivals: list[tuple[int, float]] = []  # (/lanes stamp, arrival)
        self.diag: dict[str, str] = {}
        self.reliable = reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # Raw bytes: deserialising every MarkerArray in Python held this process's GIL for ms
        # and delayed the next publish (measured: sweeps published right after a /lanes arrival
        # took 33 ms to reach the node, 9 ms otherwise).
        self.node.create_subscription(
            family.cls('visualization_msgs/msg/MarkerArray'), 'lanes',
            lambda raw: self.arrivals.append((marker_array_stamp_ns(raw), time.monotonic())),
            reliable, raw=True)
        self.node.create_subscription(
            family.cls('diagnostic_msgs/msg/DiagnosticArray'), 'diagnostics',
            lambda m: self.diag.update({kv.key: kv.value for st in m.status
                                        for kv in st.values}),
            reliable)

    def start(self) -> None:
        self.executor = SingleThreadedExecutor(context=self.node.context)
        self.executor.add_node(self.node)
        self.spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self.spinner.start()

    def wait_for(self, node: subprocess.Popen, inputs: tuple, name: str,
                 timeout_sec: float = NODE_START_TIMEOUT_SEC) -> None:
        """Until `node` (`name`) subscribes to all `inputs` (publishers): RuntimeError when it
        dies or times out."""
        deadline = time.monotonic() + timeout_sec
        while any(pub.get_subscription_count() == 0 for pub in inputs):
            if time.monotonic() > deadline or node.poll() is not None:
                raise RuntimeError(f'the {name} node did not come up')
            time.sleep(0.1)
        time.sleep(1.0)

    def close(self) -> None:
        self.executor.shutdown()
        self.spinner.join(timeout=10)
        self.node.destroy_node()


class _BenchClient(LanesClient):
    """This process's side: publishes sweeps and odometry, times /lanes, keeps /diagnostics."""

    def __init__(self, context: rclpy.Context) -> None:
        super().__init__(context, 'fhld_bench_e2e')
        self.cloud_cls = self.family.cls('sensor_msgs/msg/PointCloud2')
        self.points = self.node.create_publisher(self.cloud_cls, 'points', self.reliable)
        self.odom = self.node.create_publisher(self.family.cls('nav_msgs/msg/Odometry'), 'odom',
                                               self.reliable)
        self.start()

    def publish(self, sweeps: list[Sweep], count: int) -> dict[int, float]:
        """`count` sweeps at RATE_HZ on the wall clock; stamp -> publish time of each."""
        published: dict[int, float] = {}
        t0 = time.monotonic()
        for k in range(count):
            sweep = sweeps[k % len(sweeps)]
            stamp = START_NS + k * int(1e9 / RATE_HZ)
            header = self.family.header(stamp, 'lidar')
            cloud = create_cloud(self.cloud_cls, header, sweep.points, height=sweep.height)
            time.sleep(max(0.0, t0 + k / RATE_HZ - time.monotonic()))
            self.odom.publish(make_odometry(self.family, self.family.header(stamp, 'odom'),
                                            'lidar', sweep.sensor_to_odom))
            published[stamp] = time.monotonic()
            self.points.publish(cloud)
        return published

def _start_node() -> subprocess.Popen:
    ros_args = ['--ros-args', *[a for p in PARAMS for a in ('-p', p)]] if PARAMS else []
    return subprocess.Popen([sys.executable, '-m', 'fhld_ros.ros.lane_detector', *ros_args],
                            env=dict(os.environ),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _summary(seconds: float, published: dict[int, float], arrivals: list[tuple[int, float]],
             node_diag: dict[str, str]) -> dict[str, float]:
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
        **{f'node_{k}': float(node_diag.get(k, 0.0)) for k in NODE_COUNTERS},
    }


class _RssSampler:
    """The node's resident memory once a second while sweeps are published (a soak's memory
    must stay flat): MB medians of the first and the last third of the samples."""

    def __init__(self, pid: int) -> None:
        self.path, self.samples = f'/proc/{pid}/status', []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(1.0):
            try:
                with open(self.path) as status:
                    self.samples.append(int(status.read().split('VmRSS:')[1].split()[0]) / 1024)
            except (OSError, IndexError, ValueError):
                return  # the node is gone

    def summary(self) -> dict[str, float]:
        self.stop.set()
        self.thread.join()
        third = len(self.samples) // 3
        if not third:
            return {}
        first, last = np.median(self.samples[:third]), np.median(self.samples[-third:])
        return {'node_rss_mb_first_third': float(first), 'node_rss_mb_last_third': float(last),
                'node_rss_growth_mb': float(last - first)}


def _measure(seconds: float, dds: str) -> dict[str, float]:
    """One transport in this process: the node as a child process, sweeps, /lanes timed."""
    os.environ.update(loopback_dds_env(dds=dds))  # before the node starts and rclpy.init reads it
    sweeps = _sweeps(DISTINCT_SWEEPS)
    node = _start_node()
    context = rclpy.Context()
    rclpy.init(context=context)
    client = _BenchClient(context)
    try:
        client.wait_for(node, (client.points, client.odom), 'lane_detector')
        rss = _RssSampler(node.pid)
        published = client.publish(sweeps, int(seconds * RATE_HZ))
        memory = rss.summary()
        time.sleep(1.5)
    finally:
        node.terminate()
        node.wait(timeout=20)
        client.close()
        context.try_shutdown()
    return {**_summary(seconds, published, client.arrivals, client.diag), **memory}


def _transport_keys(dds: str, summary: dict[str, float]) -> dict[str, float]:
    """e2e_X -> e2e_{dds}_X, any other K -> e2e_{dds}_K."""
    return {f'e2e_{dds}_{k.removeprefix("e2e_")}': v for k, v in summary.items()}


def transport_child(module: str, seconds: float, dds: str,
                    env: dict[str, str] | None = None) -> dict[str, float]:
    """`python -m <module> --dds <dds> --seconds <seconds>`: one transport of a live bench in its
    own process (Fast DDS reads its profile once per process) and session, so that on a timeout
    it and the node it started go together; its summary, the last line of its stdout (JSON).
    RuntimeError with the tail of its stderr when it fails."""
    # (the child confines itself to loopback on a fresh domain: loopback_dds_env)
    child = subprocess.Popen(
        [sys.executable, '-m', module, '--dds', dds, '--seconds', str(seconds)],
        env=dict(os.environ) if env is None else env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = child.communicate(timeout=seconds + CHILD_SLACK_SEC)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        out, err = child.communicate()
        err += f'\n(timed out after {seconds + CHILD_SLACK_SEC:.0f} s)'
    lines = out.strip().splitlines()
    if child.returncode != 0 or not lines:
        tail = '\n'.join(err.strip().splitlines()[-20:])
        raise RuntimeError(f'{module} over the {dds!r} transport failed '
                           f'(exit {child.returncode}):\n{tail}')
    return json.loads(lines[-1])


def transports(dds: str | tuple[str, ...]) -> tuple[str, ...]:
    """`dds` as a tuple of PROFILES names; ValueError naming an unknown one."""
    dds = (dds,) if isinstance(dds, str) else tuple(dds)
    unknown = [name for name in dds if name not in PROFILES]
    if unknown:
        raise ValueError(f'unknown DDS transport {", ".join(unknown)} '
                         f'(choose from {", ".join(PROFILES)})')
    return dds


def bench_e2e(seconds: float = SECONDS,
              dds: tuple[str, ...] = ('project', 'default')) -> dict[str, float]:
    """The node end to end over each transport in `dds`, one after the other."""
    results: dict[str, float] = {}
    env = dict(os.environ, FHLD_BENCH_E2E_PARAMS=' '.join(PARAMS))
    for name in transports(dds):
        results.update(_transport_keys(name, transport_child(
            'fhld_ros.commands.bench_e2e', seconds, name, env)))
    return results


def transport_main(section: str, measure: Callable[[float, str], dict],
                   seconds: float) -> None:
    """The command line of transport_child's process: `measure(seconds, dds)` printed as one
    JSON line last on stdout."""
    parser = argparse.ArgumentParser(description=f'one transport of `fhld bench {section}`: '
                                     'its summary as one JSON line last on stdout')
    parser.add_argument('--dds', choices=list(PROFILES), default='project')
    parser.add_argument('--seconds', type=float, default=seconds)
    cli = parser.parse_args()
    print(json.dumps(measure(cli.seconds, cli.dds)), flush=True)


if __name__ == '__main__':
    transport_main('e2e', _measure, SECONDS)
