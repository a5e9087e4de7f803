"""`fhld simulate`: the bag reads back with rosbags and with mcap_ros2, is self-contained,
the preview is written, and bad arguments give one clear error line and no output."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from fhld_ros.bagio import bag_topics, read_messages
from fhld_ros.cli import main
from fhld_ros.sim.simulator import Simulator
from msg_adapters.lanes import marker_array_to_lanes
from msg_adapters.odometry import odometry_to_matrix
from msg_adapters.pointcloud2 import read_points, read_xyzi

SMALL = ['--seed', '4', '--sweeps', '12', '--sensor', 'os1-32', '--columns', '256', '--quiet']


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp('sim')
    path, png = out / 'drive', out / 'preview.png'
    assert main(['simulate', str(path), *SMALL, '--preview', str(png)]) == 0
    return path, png


def test_bag_reads_back_with_rosbags(bag: tuple[Path, Path]) -> None:
    path, png = bag
    assert bag_topics(path) == {'/points': 'sensor_msgs/msg/PointCloud2',
                                '/odom': 'nav_msgs/msg/Odometry',
                                '/lanes_gt': 'visualization_msgs/msg/MarkerArray'}
    msgs: dict[str, list] = {}
    for topic, stamp, msg in read_messages(path):
        msgs.setdefault(topic, []).append((stamp, msg))
    assert len(msgs['/points']) == len(msgs['/odom']) == 12
    assert len(msgs['/lanes_gt']) == 2  # all lines at the start, then once a second
    sim = Simulator(4, sweeps=12, sensor='os1-32', columns=256)
    for (stamp, cloud), (odom_stamp, odom), sweep in zip(msgs['/points'], msgs['/odom'],
                                                         sim.sweeps()):
        assert stamp == odom_stamp == sweep.stamp_ns
        assert odom.header.frame_id == 'odom'
        assert odom.child_frame_id == cloud.header.frame_id == 'lidar'
        assert np.allclose(odometry_to_matrix(odom), sweep.odom_pose)
        assert (cloud.height, cloud.width, cloud.point_step) == (32, 256, 48)
        assert read_points(cloud).tobytes() == sweep.points.tobytes()
        xyz, intensity = read_xyzi(cloud)
        assert xyz.shape[0] == np.count_nonzero(sweep.labels)
    first = marker_array_to_lanes(msgs['/lanes_gt'][0][1])
    assert first.frame_id == 'odom' and len(first.lanes) == len(sim.scene.lane_lines)
    assert all(np.allclose(a, b) for a, b in zip(first.lanes, sim.scene.lane_lines))
    assert np.all(first.confidences == 1.0) and first.window_outline is None
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 10_000


def test_bag_reads_back_with_mcap_ros2(bag: tuple[Path, Path]) -> None:
    (mcap_file,) = bag[0].glob('*.mcap')
    counts: Counter = Counter()
    with mcap_file.open('rb') as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]
                                              ).iter_decoded_messages():
            counts[channel.topic] += 1
            if channel.topic == '/odom':
                assert msg.child_frame_id == 'lidar' and msg.header.frame_id == 'odom'
            elif channel.topic == '/points':
                assert (msg.height, msg.width) == (32, 256)
                assert [f.name for f in msg.fields][:3] == ['x', 'y', 'z']
                xyz, _ = read_xyzi(msg)
                assert xyz.shape[0] > 1000
            else:
                assert all(m.header.frame_id == 'odom' for m in msg.markers)
    assert counts == {'/points': 12, '/odom': 12, '/lanes_gt': 2}


@pytest.mark.parametrize('extra, text', [
    (['--sweeps', '0'], '--sweeps'),
    (['--sweeps', '999999'], '--sweeps'),
    (['--seed', '-3'], '--seed'),
    (['--speed', '31'], '--speed'),
    (['--columns', '10'], '--columns'),
    (['--odom-noise', '-1'], '--odom-noise'),
    (['--preview', 'picture.jpg'], '.png'),
    (['--frame-id', 'odom'], '--frame-id'),
])
def test_bad_arguments_give_one_clear_line(tmp_path: Path, capsys: pytest.CaptureFixture,
                                           extra: list[str], text: str) -> None:
    out = tmp_path / 'bag'
    assert main(['simulate', str(out), '--sweeps', '1', '--quiet', *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('fhld simulate: error:') and text in err[0]
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_existing_bag_and_missing_directory(tmp_path: Path, capsys: pytest.CaptureFixture
                                            ) -> None:
    out = tmp_path / 'bag'
    out.mkdir()
    assert main(['simulate', str(out), '--sweeps', '1', '--quiet']) == 2
    assert 'exists' in capsys.readouterr().err
    assert main(['simulate', str(tmp_path / 'no' / 'bag'), '--sweeps', '1', '--quiet']) == 2
    assert 'does not exist' in capsys.readouterr().err


def test_unknown_choice_is_rejected_by_the_parser(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(['simulate', str(tmp_path / 'bag'), '--sensor', 'hdl-9000'])
    assert exc.value.code == 2
    assert 'invalid choice' in capsys.readouterr().err
