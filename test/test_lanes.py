"""msg_adapters.lanes: the /lanes MarkerArray and Path contract (docs/design.md §3)."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from msg_adapters.family import rclpy_family, rosbags_family
from msg_adapters.lanes import (
    DELETEALL,
    LINE_STRIP,
    lane_to_path,
    lanes_to_marker_array,
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
