"""camera_lane_detector in a graph as a user's camera drives it: a separate process with plain
rclpy publishers (test/camera_publisher.py) sends camera_info and 960x540 images at 10 Hz, one
of them cut short, to `python -m fhld_ros.ros.camera_lane_detector`; this process listens to
/lanes and /diagnostics.

rgb8 Images (1.5 MB each) on both transports of fhld_ros/ros/env.py: the project's 32 MB
shared-memory profile, and Fast DDS's default 512 kB segment, where an image travels as UDP
fragments; JPEGs through image_transport's compressed topic (image_transport:=compressed); and
a driver that latches its camera_info (once, transient local) before the node starts.
The weights decode one lane in every image (model_fixtures.lane_everywhere_salad).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from model_fixtures import lane_everywhere_salad
from ros_helpers import NodeOutputs, stop, wait_until

from fhld_ros.ros.env import loopback_dds_env
from msg_adapters.lanes import marker_array_to_lanes

pytestmark = [pytest.mark.ros, pytest.mark.slow]

FRAMES = 20
PUBLISHER = Path(__file__).resolve().parent / 'camera_publisher.py'
GRAPHS = [('project', 'raw', 'streamed'), ('default', 'raw', 'streamed'),
          ('project', 'compressed', 'streamed'), ('project', 'raw', 'latched')]


@pytest.fixture(scope='module')
def weights(tmp_path_factory) -> Path:
    return lane_everywhere_salad(tmp_path_factory.mktemp('camera_graph') / 'salad.pt')


@pytest.mark.parametrize('dds, transport, info', GRAPHS, ids=lambda v: v)
def test_every_image_from_a_separate_driver_gets_its_lanes(dds, transport, info, weights,
                                                           ros_env, rclpy_context):
    # this process's listener keeps the project profile (Fast DDS reads it once per process);
    # it only takes the small outputs
    env = loopback_dds_env(domain_id=int(ros_env['ROS_DOMAIN_ID']), base=ros_env, dds=dds)
    publisher = subprocess.Popen(
        [sys.executable, str(PUBLISHER), '--frames', str(FRAMES), '--corrupt-after', '5',
         *(['--jpeg'] if transport == 'compressed' else []),
         *(['--latched-info'] if info == 'latched' else []), '--go-on-stdin'],
        env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    node = subprocess.Popen(
        [sys.executable, '-m', 'fhld_ros.ros.camera_lane_detector', '--ros-args',
         '-p', f'checkpoint:={weights}', '-p', f'image_transport:={transport}'],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    listener = NodeOutputs(rclpy_context, 'camera_graph_listener', depth=100)
    try:
        assert wait_until(lambda: listener.diagnostics, 90), 'the node never came up'
        out, err = publisher.communicate('go\n', timeout=120)  # this listener is ready too
        assert publisher.returncode == 0, err
        stamps = json.loads(out.strip().splitlines()[-1])['stamps']

        def lanes_stamps() -> set[int]:
            return {marker_array_to_lanes(m).stamp_ns for m in list(listener.lanes)}

        def values() -> dict[str, str]:
            return listener.diagnostic_values()
        wait_until(lambda: int(values().get('images', 0)) + int(values().get('bad_images', 0))
                   >= FRAMES + 1 and int(values().get('detections', 0)) >= len(lanes_stamps())
                   and set(stamps) <= lanes_stamps(), 10)
        assert node.poll() is None, 'the node died'
        lost = sorted(set(stamps) - lanes_stamps())
        report = (f'{dds} {transport} {info}: {len(lost)} of {FRAMES} images without /lanes; '
                  f'{values()}')
        print(report)
        assert lanes_stamps() <= set(stamps), report
        assert (values()['images'], values()['bad_images']) == (str(FRAMES), '1'), report
        assert values()['last_error'].startswith('bad_images: '), report
        assert int(values().get('images_lost_in_dds', 0)) == 0, report
        if info == 'latched':  # its one message, sent before the node started
            assert values()['camera_infos'] == '1', report
        # an image without /lanes must be one a newer image overtook while a detection ran
        # (the newest wins); the last one is always detected
        assert len(lost) == int(values()['images_overtaken']) and stamps[-1] not in lost, report
        if float(values()['latency_ms_p95']) < 80:  # the machine kept up
            assert not lost, report
    finally:
        listener.close()
        stop(node)
        stop(publisher)
