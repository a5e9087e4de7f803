"""msg_adapters.lanes: the /lanes MarkerArray and Path contract (docs/design.md §3)."""
from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import MarkerArray

from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.lanes import (
    DELETEALL,
    LINE_STRIP,
    lane_to_path,
    lane_to_path_cdr,
    lanes_to_marker_array,
    lanes_to_marker_array_cdr,
    marker_array_stamp_ns,
    marker_array_to_lanes,
)

FAMILIES = [rosbags_family(), rclpy_family()]
OUTLINE = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [-1, -1, 0]], float)


def _lanes():
    s = np.linspace(0, 10, 11)
    return [np.stack([s, np.full_like(s, 1.8), -1.9 + 0.01 * s], 1),
            np.stack([s, np.full_like(s, -1.7), np.full_like(s, -1.9)], 1)]


@pytest.mark.parametrize('family', FAMILIES, ids=lambda f: f.name)
def test_marker_array_follows_the_contract(family):
    header = family.header(1_500_000_000, 'odom')
    msg = lanes_to_marker_array(family, header, _lanes(), [0.93, 0.5], [4, 9], OUTLINE)
    first, *strips, window = msg.markers
    assert first.action == DELETEALL and first.ns == 'lanes'
    assert [m.ns for m in strips] == ['lanes', 'lanes'] and [m.id for m in strips] == [4, 9]
    assert all(m.type == LINE_STRIP and m.header.frame_id == 'odom' for m in msg.markers[1:])
    assert strips[0].text == 'conf=0.93' and strips[0].color.a == pytest.approx(0.93)
    assert window.ns == 'bev_window' and len(window.points) == 5
    assert strips[0].points[3].z == pytest.approx(-1.87)
    back = marker_array_to_lanes(msg)
    assert back.frame_id == 'odom' and back.stamp_ns == 1_500_000_000
    np.testing.assert_allclose(back.lanes[0], _lanes()[0])
    np.testing.assert_allclose(back.confidences, [0.93, 0.5])
    np.testing.assert_array_equal(back.ids, [4, 9])
    np.testing.assert_allclose(back.window_outline, OUTLINE)


def test_no_lanes_still_clears_and_outlines():
    family = rosbags_family()
    msg = lanes_to_marker_array(family, family.header(0, 'odom'), [], [], [], OUTLINE)
    assert [m.ns for m in msg.markers] == ['lanes', 'bev_window']
    back = marker_array_to_lanes(msg)
    assert back.lanes == [] and back.window_outline is not None


def test_mismatched_inputs_are_rejected():
    family = rosbags_family()
    with pytest.raises(ValueError, match='must match'):
        lanes_to_marker_array(family, family.header(0, 'o'), _lanes(), [1.0], [1, 2])
    with pytest.raises(ValueError, match=r'\(5, 3\)'):
        lanes_to_marker_array(family, family.header(0, 'o'), [], [], [], OUTLINE[:4])


@pytest.mark.parametrize('family', FAMILIES, ids=lambda f: f.name)
def test_path_follows_the_lane_with_headings(family):
    lane = np.array([[0, 0, 0], [1, 1, 0], [2, 2, 0.1]], float)
    path = lane_to_path(family, family.header(3, 'odom'), lane)
    assert len(path.poses) == 3 and path.header.frame_id == 'odom'
    assert path.poses[2].pose.position.z == pytest.approx(0.1)
    q = path.poses[0].pose.orientation
    assert 2 * np.arctan2(q.z, q.w) == pytest.approx(np.pi / 4)
    assert len(lane_to_path(family, family.header(3, 'odom'), None).poses) == 0


def test_bench_reads_the_stamp_of_a_serialised_marker_array():
    family = rclpy_family()
    stamp = 1_700_000_123_456_789_012
    msg = lanes_to_marker_array(family, family.header(stamp, 'odom'), _lanes(), [0.9, 0.8],
                                [1, 2], OUTLINE)
    assert marker_array_stamp_ns(serialize_message(msg)) == stamp
    with pytest.raises(ValueError, match='without markers'):
        marker_array_stamp_ns(serialize_message(family.cls('visualization_msgs/msg/MarkerArray')()))


@pytest.mark.parametrize('trial', range(40))
def test_cdr_bytes_are_the_messages_serialised(trial):
    """The bytes the node publishes and replay stores: rosbags' serialisation of the same
    message byte for byte (rclpy leaves its padding bytes uninitialised, so against rclpy the
    check is its deserialisation), for any count of lanes and points, odd frame ids included."""
    rng = np.random.default_rng(trial)
    family = rosbags_family()
    count = int(rng.integers(0, 5))
    lanes = [rng.normal(size=(int(rng.integers(0, 30)), 3)) for _ in range(count)]
    conf, ids = rng.uniform(-0.1, 1.1, count), rng.integers(0, 3000, count)
    frame, stamp = 'f' * int(rng.integers(0, 9)), int(rng.integers(0, 2**40))
    outline = OUTLINE + rng.normal(size=(5, 3)) if trial % 3 else None
    header = family.header(stamp, frame)
    data = lanes_to_marker_array_cdr(stamp, frame, lanes, conf, ids, outline)
    expected = lanes_to_marker_array(family, header, lanes, conf, ids, outline)
    assert data == bytes(family.typestore.serialize_cdr(
        expected, 'visualization_msgs/msg/MarkerArray'))
    back = marker_array_to_lanes(deserialize_message(data, MarkerArray))
    assert (back.stamp_ns, back.frame_id) == (stamp, frame)
    assert len(back.lanes) == count and list(back.ids) == list(ids)
    for got, lane in zip(back.lanes, lanes):
        np.testing.assert_array_equal(got, lane.reshape(-1, 3))
    lane = lanes[0][:trial % 4] if lanes else None  # 0-3 poses or none
    data = lane_to_path_cdr(stamp, frame, lane)
    assert data == bytes(family.typestore.serialize_cdr(lane_to_path(family, header, lane),
                                                        'nav_msgs/msg/Path'))
    path = deserialize_message(data, Path)
    assert path == lane_to_path(rclpy_family(), rclpy_family().header(stamp, frame), lane)
