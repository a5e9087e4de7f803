"""The node in a graph as a user's stack drives it (issues #17, #34): a separate process with plain
rclpy publishers (test/graph_publisher.py) sends /odom and /points at 10 Hz to
`python -m fhld_ros.ros.lane_detector`; this process listens to /lanes and /diagnostics.

Both run on each transport of fhld_ros/ros/env.py: the project's 32 MB shared-memory profile,
and Fast DDS's default 512 kB segment, where a 3 MB cloud travels as 64 kB fragments.

Measured before the fixes: 9-13 of 40 sweeps dropped as bad clouds ("no odometry around cloud
stamp") with /odom published before /points at identical stamps (project profile); on the
default segment /lanes for 18-26 of 40 sweeps and "odometry stopped" although every pose was
published before its cloud (a reliable odometry reader held each pose behind a lost one for
up to 3 s).
"""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from ros_helpers import NodeOutputs, stop, wait_until

from fhld_ros.ros.env import loopback_dds_env
from msg_adapters.lanes import marker_array_to_lanes

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SWEEPS = 40
MALFORMED = 2
# A light window (25.6 m at 10 cm; classical detector) keeps each detection well under the
# 100 ms sweep period on a loaded 2-core machine: a sweep skipped for want of CPU is not what
# this test is about (measured at 640 px: 150 ms per detection under load, 14 of 40 skipped).
SIZE_PX = 256
PUBLISHER = Path(__file__).resolve().parent / 'graph_publisher.py'


@dataclass(frozen=True)
class Graph:
    dds: str  # fhld_ros.ros.env.PROFILES
    odom_hz: int  # 10: the clouds' stamps; more: odometry on its own stamps
    best_effort: bool = False  # the publishers' reliability (LiDAR drivers: best effort)

    def __str__(self) -> str:
        return f'{self.dds}-{self.odom_hz}hz' + ('-best-effort' if self.best_effort else '')


GRAPHS = [Graph('project', 10), Graph('project', 50), Graph('project', 10, best_effort=True),
          Graph('default', 10), Graph('default', 200)]


@pytest.fixture
def graph_env(graph, ros_env) -> dict[str, str]:
    """This run's domain on the graph's transport (this process's listener keeps the project
    profile: Fast DDS reads it once per process; it only takes the small outputs)."""
    return loopback_dds_env(domain_id=int(ros_env['ROS_DOMAIN_ID']), base=ros_env, dds=graph.dds)


@pytest.fixture
def node_process(graph_env):
    node = subprocess.Popen(
        [sys.executable, '-m', 'fhld_ros.ros.lane_detector', '--ros-args',
         '-p', 'detector:=classical', '-p', f'size_px:={SIZE_PX}', '-p', 'resolution_m:=0.1'],
        env=graph_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield node
    stop(node)


def _run_publisher(graph: Graph, env: dict[str, str]) -> list[int]:
    done = subprocess.run(
        [sys.executable, str(PUBLISHER), '--odom-hz', str(graph.odom_hz), '--sweeps', str(SWEEPS),
         '--malformed', str(MALFORMED), *(['--best-effort'] if graph.best_effort else [])],
        env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    stamps = json.loads(done.stdout.strip().splitlines()[-1])['stamps']
    assert len(stamps) == SWEEPS
    return stamps


@pytest.mark.parametrize('graph', GRAPHS, ids=str)
def test_every_sweep_from_a_separate_publisher_gets_its_lanes(graph, graph_env, node_process,
                                                              rclpy_context):
    listener = NodeOutputs(rclpy_context, 'graph_listener', depth=100)
    try:
        assert wait_until(lambda: listener.diagnostics, 60), 'the node never came up'
        stamps = _run_publisher(graph, graph_env)

        def lanes_stamps() -> set[int]:
            return {marker_array_to_lanes(m).stamp_ns for m in list(listener.lanes)}
        wait_until(lambda: set(stamps) <= lanes_stamps(), 10)
        wait_until(lambda: int(listener.diagnostic_values().get('clouds_received', 0))
                   >= SWEEPS + MALFORMED, 5)
        assert node_process.poll() is None, 'the node died'
        values = listener.diagnostic_values()
        lost = sorted(set(stamps) - lanes_stamps())
        report = (f'{graph}: {len(lost)} of {SWEEPS} sweeps without /lanes: '
                  f'{[(s - stamps[0]) // 1_000_000 for s in lost]} ms; {values}')
        print(report)
        # every sweep went into the grid in the odometry frame: none lost to odometry timing
        assert int(values.get('bad_clouds', 0)) == MALFORMED, report
        assert int(values['clouds']) == SWEEPS, report
        assert int(values.get('clouds_lost_in_dds', 0)) == 0, report
        assert int(values.get('odometry_timeouts', 0)) == 0, report
        # On the default segment DDS loses 10-45 % of these poses (the publisher's 3 MB cloud
        # overruns the segment the pose waits in); a sweep whose pose was lost goes in with
        # the motion of the poses before continued. Only a first sweep whose pose was lost
        # before any other arrived has nothing to extrapolate from: it goes in alone.
        frames = [m.markers[0].header.frame_id for m in sorted(
            listener.lanes, key=lambda m: marker_array_to_lanes(m).stamp_ns)]
        alone = int(values.get('clouds_without_odometry', 0))
        if graph.dds == 'default' and alone == 1 and frames[0] == 'os_lidar':
            frames = frames[1:]
        else:
            assert alone == 0, report
        assert set(frames) == {'odom'}, frames
        # A sweep without /lanes must be one a newer sweep superseded while a detection ran
        # (overload: the latest sweep wins), never one that waited for odometry. With the
        # executor's spin beside it a detection took 90-110 ms in the node on the loaded
        # 2-core machine (15 ms alone), so some are superseded at 10 Hz. On the default
        # segment a run of three poses lost in a row outlasts the extrapolation's reach, and
        # the sweep waiting for the next pose is overtaken when that pose lets both in.
        assert len(lost) == int(values['sweeps_skipped']), report
        if float(values['latency_ms_p95']) < 90:  # the machine kept up
            assert len(lost) <= (SWEEPS // 10 if graph.dds == 'default' else 0), report
    finally:
        listener.close()


@pytest.mark.parametrize('graph', [Graph('default', 10, best_effort=True)], ids=str)
def test_clouds_that_dds_loses_are_counted_and_named(graph, graph_env, node_process,
                                                     rclpy_context):
    """A best-effort driver's 3 MB clouds over the default 512 kB segment: DDS loses most of
    them before any subscriber (measured with a plain rclpy subscriber: 18-28 of 100 arrive,
    none with 200 Hz odometry beside them). The node cannot bring them back; it must say so:
    DDS reports each gap between the clouds that did arrive (not those lost before the first
    or after the last), the node counts them, and /diagnostics names the loss."""
    listener = NodeOutputs(rclpy_context, 'graph_listener', depth=100)
    try:
        assert wait_until(lambda: listener.diagnostics, 60), 'the node never came up'
        _run_publisher(graph, graph_env)
        sent = SWEEPS + MALFORMED
        seen = len(listener.diagnostics)  # statuses come once a second: two more are after
        assert wait_until(lambda: len(listener.diagnostics) >= seen + 2, 5)  # the last cloud
        assert node_process.poll() is None, 'the node died'
        values = listener.diagnostic_values()
        received = int(values.get('clouds_received', 0))
        lost = int(values.get('clouds_lost_in_dds', 0))
        assert values['input_reliability'] == 'BEST_EFFORT', values
        assert received + lost <= sent, values  # nothing counted twice
        if received < sent - 2:  # more than the ends lost: some gap was reported
            assert lost > 0, values
        if lost:
            assert any('lost by DDS' in m.status[0].message
                       for m in list(listener.diagnostics)), values
    finally:
        listener.close()
