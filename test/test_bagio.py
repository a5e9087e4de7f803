"""fhld_ros.bagio: MCAP bags written atomically and read back with clear errors."""
from __future__ import annotations

import numpy as np
import pytest

from fhld_ros.bagio import BagError, BagWriter, bag_topics, read_messages
from msg_adapters.lanes import lanes_to_marker_array, marker_array_to_lanes


def _write(path, count=3):
    with BagWriter(path) as writer:
        family = writer.family
        for k in range(count):
            msg = lanes_to_marker_array(family, family.header(k, 'odom'),
                                        [np.ones((2, 3)) * k], [1.0], [k])
            writer.write('/lanes_gt', 'visualization_msgs/msg/MarkerArray', k * 100, msg)


def test_round_trip(tmp_path):
    _write(tmp_path / 'bag')
    assert bag_topics(tmp_path / 'bag') == {'/lanes_gt': 'visualization_msgs/msg/MarkerArray'}
    got = list(read_messages(tmp_path / 'bag', ['/lanes_gt']))
    assert [stamp for _, stamp, _ in got] == [0, 100, 200]
    assert marker_array_to_lanes(got[2][2]).lanes[0][0, 0] == 2


def test_failure_leaves_nothing_behind(tmp_path):
    with pytest.raises(RuntimeError):
        with BagWriter(tmp_path / 'bag') as writer:
            writer.write('/a', 'std_msgs/msg/Header', 0, writer.family.header(0, 'x'))
            raise RuntimeError('boom')
    assert list(tmp_path.iterdir()) == []


def test_clear_errors(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        list(read_messages(tmp_path / 'missing'))
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'x.mcap').write_bytes(b'not a bag')
    with pytest.raises(BagError, match='cannot read bag'):
        list(read_messages(tmp_path / 'junk'))
    _write(tmp_path / 'bag')
    with pytest.raises(BagError, match='no topic /points'):
        list(read_messages(tmp_path / 'bag', ['/points']))
    with pytest.raises(BagError, match='directory'):
        with BagWriter(tmp_path / 'nope' / 'bag'):
            pass
