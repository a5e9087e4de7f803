"""The node in a graph as a user's stack drives it (issue #17): a separate process with plain
rclpy publishers (test/graph_publisher.py) sends /odom and /points at 10 Hz to
`python -m fhld_ros.ros.lane_detector`; this process listens to /lanes and /diagnostics.

Measured before the fix: 9-13 of 40 sweeps dropped as bad clouds ("no odometry around cloud
stamp") with /odom published before /points at identical stamps.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from ros_helpers import NodeOutputs, wait_until

from msg_adapters.lanes import marker_array_to_lanes

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SWEEPS = 40
# A light window (25.6 m at 10 cm; classical detector) keeps each detection well under the
# 100 ms sweep period on a loaded 2-core machine: a sweep skipped for want of CPU is not what
# this test is about (measured at 640 px: 150 ms per detection under load, 14 of 40 skipped).
SIZE_PX = 256
PUBLISHER = Path(__file__).resolve().parent / 'graph_publisher.py'


@pytest.fixture
def node_process(ros_env):
    node = subprocess.Popen(
        [sys.executable, '-m', 'fhld_ros.ros.lane_detector', '--ros-args',
         '-p', 'detector:=classical', '-p', f'size_px:={SIZE_PX}', '-p', 'resolution_m:=0.1'],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield node
    if node.poll() is None:
        node.terminate()
    try:
        node.wait(timeout=20)
    except subprocess.TimeoutExpired:
        node.kill()
        node.wait()


@pytest.mark.parametrize('odom_hz', [10, 50])
def test_every_sweep_from_a_separate_publisher_gets_its_lanes(odom_hz, node_process, ros_env,
                                                              rclpy_context):
    listener = NodeOutputs(rclpy_context, 'graph_listener', depth=100)
    try:
        assert wait_until(lambda: listener.diagnostics, 60), 'the node never came up'
        done = subprocess.run([sys.executable, str(PUBLISHER), '--odom-hz', str(odom_hz),
                               '--sweeps', str(SWEEPS)], env=ros_env, capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        stamps = json.loads(done.stdout.strip().splitlines()[-1])['stamps']
        assert len(stamps) == SWEEPS

        def lanes_stamps() -> set[int]:
            return {marker_array_to_lanes(m).stamp_ns for m in list(listener.lanes)}
        wait_until(lambda: set(stamps) <= lanes_stamps(), 10)
        wait_until(lambda: int(listener.diagnostic_values().get('clouds', 0)) >= SWEEPS, 5)
        assert node_process.poll() is None, 'the node died'
        values = listener.diagnostic_values()
        lost = sorted(set(stamps) - lanes_stamps())
        report = (f'{len(lost)} of {SWEEPS} sweeps without /lanes: '
                  f'{[(s - stamps[0]) // 1_000_000 for s in lost]} ms; {values}')
        print(report)
        # every sweep went into the grid in the odometry frame: none lost to odometry timing
        assert int(values.get('bad_clouds', 0)) == 0, report
        assert int(values['clouds']) == SWEEPS, report
        assert int(values.get('clouds_without_odometry', 0)) == 0, report
        assert int(values.get('odometry_timeouts', 0)) == 0, report
        # A sweep without /lanes must be one a newer sweep superseded while a detection ran
        # (overload: the latest sweep wins), never one that waited for odometry. With the
        # executor's spin beside it a detection took 90-110 ms in the node on the loaded
        # 2-core machine (15 ms alone), so some are superseded at 10 Hz.
        assert len(lost) == int(values['sweeps_skipped']), report
        if float(values['latency_ms_p95']) < 90:  # the machine kept up: no sweep superseded
            assert not lost, report
        frames = {m.markers[0].header.frame_id for m in listener.lanes}
        assert frames == {'odom'}, frames
    finally:
        listener.close()
