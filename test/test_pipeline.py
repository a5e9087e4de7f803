"""fhld_ros.pipeline: poses, frames, ids, ego lane and the detection cadence."""
from __future__ import annotations

import numpy as np
import pytest

from fhld_ros.lane_output import LaneIdTracker, ego_lane_bounds, mean_distances
from fhld_ros.parameters import DetectorParams
from fhld_ros.pipeline import LanePipeline
from fhld_ros.pose_buffer import PoseBuffer
from msg_adapters.family import rosbags_family
from msg_adapters.odometry import euler_to_matrix, make_odometry
from msg_adapters.pointcloud2 import create_cloud

FAMILY = rosbags_family()
S = np.linspace(-10, 10, 41)


def _line(y):
    return np.stack([S, np.full_like(S, y), np.full_like(S, -1.8)], 1)


class FixedLanes:
    """A detector that sees the same lanes in every window frame."""

    def __init__(self, lanes, confidences):
        self.lanes, self.confidences, self.windows = lanes, np.asarray(confidences), []

    def __call__(self, window):
        self.windows.append(window)
        return self.lanes, self.confidences


def _cloud(stamp_ns, frame='lidar', n=200):
    rng = np.random.default_rng(stamp_ns % 1000)
    points = np.zeros(n, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    points['x'], points['y'] = rng.uniform(-10, 10, n), rng.uniform(-10, 10, n)
    points['z'], points['intensity'] = -1.8, rng.uniform(0, 1, n)
    return create_cloud(FAMILY.cls('sensor_msgs/msg/PointCloud2'),
                        FAMILY.header(stamp_ns, frame), points)


def _odom(stamp_ns, pose, child='lidar'):
    return make_odometry(FAMILY, FAMILY.header(stamp_ns, 'odom'), child, pose)


def test_pose_buffer_interpolates_inside_and_refuses_outside_and_across_gaps():
    buffer = PoseBuffer()
    buffer.add(1_400_000_000, euler_to_matrix(4, 0, 0, 0, 0, 0))
    buffer.add(1_000_000_000, euler_to_matrix(0, 0, 0, 0, 0, 0))  # out of order is fine
    np.testing.assert_allclose(buffer.at(1_100_000_000)[:3, 3], [1, 0, 0])
    np.testing.assert_allclose(buffer.at(1_400_000_000)[:3, 3], [4, 0, 0])
    assert buffer.at(1_400_000_001) is None and buffer.at(999_999_999) is None  # no hold
    buffer.add(2_500_000_000, euler_to_matrix(9, 0, 0, 0, 0, 0))
    assert buffer.at(1_900_000_000) is None  # 1.1 s between poses: odometry stopped there
    # old poses leave by age, and all of them when time goes back
    buffer.add(7_000_000_000, np.eye(4))
    assert buffer.stamps == [2_500_000_000, 7_000_000_000]
    # a late pose inside the kept span goes in (once); one before it all means a new run
    assert buffer.add(4_000_000_000, np.eye(4)) and not buffer.add(4_000_000_000, np.eye(4))
    assert buffer.stamps == [2_500_000_000, 4_000_000_000, 7_000_000_000]
    buffer.add(100, np.eye(4))
    assert buffer.stamps == [100]


def test_lane_ids_survive_small_motion_and_new_lanes_get_new_ids():
    tracker = LaneIdTracker()
    first = tracker.assign([_line(1.8), _line(-1.7)])
    second = tracker.assign([_line(-1.6), _line(5.3), _line(1.9)])
    assert second[0] == first[1] and second[2] == first[0]
    assert second[1] not in first
    # lanes that overlap nothing from before (an infeasible assignment) all get fresh ids
    far = tracker.assign([_line(1.8) + [100, 0, 0], _line(-1.7) + [100, 0, 0]])
    assert not set(far) & set(second)


def test_mean_distances_of_every_pair_over_their_overlap():
    ahead = np.stack([np.arange(0.0, 10.5, 0.5), np.zeros(21), np.zeros(21)], 1)
    beside = ahead + [0, 0.3, 5.0]  # 0.3 m to the side; height is not counted
    longer = np.stack([np.arange(-5.0, 30.0, 0.25), np.full(140, -1.0), np.zeros(140)], 1)
    apart = ahead + [0, 3.0, 0]  # nothing within 2 m
    half = ahead[:11] + [5.0, 0.0, 0.0]  # x 5-10 m: overlaps the second half of `ahead`
    cost = mean_distances([ahead, longer, np.zeros((0, 3)), half], [beside, apart, ahead])
    assert cost.shape == (4, 3)
    assert np.allclose(cost[0], [0.3, np.inf, 0.0])
    # longer's points between beside's samples and past its ends count while within 2 m
    gap = np.linalg.norm(longer[:, None, :2] - beside[None, :, :2], axis=-1).min(1)
    assert np.isclose(cost[1, 0], gap[gap < 2].mean()) and 1.3 < cost[1, 0] < 1.4
    assert cost[1, 1] == np.inf
    assert np.all(cost[2] == np.inf)  # an empty lane overlaps nothing
    assert np.allclose(cost[3], [0.3, np.inf, 0.0])
    # from ahead's points only those within 2 m of `half` count: its 11 on it, and 3.5-4.5 m
    assert np.allclose(mean_distances([ahead], [half]), (0.5 + 1.0 + 1.5) / 14)
    assert mean_distances([], [ahead]).shape == (0, 1)


def test_ego_lane_bounds_pick_the_nearest_line_each_side():
    lanes = [_line(5.3), _line(1.8), _line(-1.7), _line(-5.2)]
    assert ego_lane_bounds(lanes) == (1, 2)
    far = [np.stack([S + 30, np.full_like(S, 1.0), S * 0], 1)]
    assert ego_lane_bounds(far) == (None, None)


def test_lanes_come_out_in_the_odometry_frame_with_the_window_outline():
    detector = FixedLanes([_line(1.8), _line(-1.7), _line(4.0)], [0.9, 0.8, 0.2])
    pipeline = LanePipeline(DetectorParams(size_px=256, resolution_m=0.1), detector)
    pose = euler_to_matrix(100.0, 50.0, 2.0, 0, 0, np.pi / 2)
    pipeline.add_odometry(_odom(1_000_000_000, pose))
    intake = pipeline.add_cloud(_cloud(1_000_000_000))
    assert set(intake.timings_ms) == {'decode_ms', 'grid_insert_ms'}
    assert intake.stamp_ns == 1_000_000_000 and intake.let_in == [1_000_000_000]
    out = pipeline.detect()
    assert out.frame_id == 'odom' and out.stamp_ns == 1_000_000_000
    assert len(out.lanes) == 2  # the 0.2 lane is under score_threshold 0.5
    # window x (forward) is odom +y after a 90 deg yaw; window y=1.8 is odom x = 100 - 1.8
    np.testing.assert_allclose(out.lanes[0][:, 0], 100 - 1.8, atol=1e-6)
    np.testing.assert_allclose(out.lanes[0][:, 1], 50 + S, atol=1e-6)
    np.testing.assert_allclose(out.outline[0], out.outline[4])
    assert np.abs(out.outline[:4, :2] - [100, 50]).max() == pytest.approx(12.8)
    assert out.ego_left is out.lanes[0] and out.ego_right is out.lanes[1]
    assert pipeline.detect() is None  # nothing new since the last cycle


def test_the_lanes_a_detector_dropped_for_want_of_paint_are_counted():
    detector = FixedLanes([_line(1.8)], [0.9])
    detector.lanes_unpainted = 2  # as fhld_detector's paint check reports them
    pipeline = LanePipeline(DetectorParams(size_px=256, resolution_m=0.1), detector,
                            expect_odometry=False)
    for stamp_ns in (1_000_000_000, 1_100_000_000):
        pipeline.add_cloud(_cloud(stamp_ns))
        assert pipeline.detect() is not None
    assert pipeline.counters['lanes_unpainted'] == 4


def test_cloud_in_another_frame_uses_the_static_extrinsic():
    detector = FixedLanes([], [])
    params = DetectorParams(size_px=64, resolution_m=0.5, lidar_to_base=(1.0, 0, 2.0, 0, 0, 0))
    pipeline = LanePipeline(params, detector)
    pipeline.add_odometry(_odom(0, euler_to_matrix(10, 0, 0, 0, 0, 0), child='base_link'))
    pipeline.add_cloud(_cloud(0, frame='lidar'))
    out = pipeline.detect()
    np.testing.assert_allclose(detector.windows[0].window_to_output[:3, 3], [11, 0, 2])
    assert out.frame_id == 'odom'


def test_without_odometry_each_sweep_stands_alone_in_the_cloud_frame():
    detector = FixedLanes([_line(1.8)], [0.9])
    params = DetectorParams(size_px=64, resolution_m=0.5, odom_wait_sec=0.25)
    pipeline = LanePipeline(params, detector)
    for k in range(3):  # the first sweeps wait odom_wait_sec in case odometry is on its way
        pipeline.add_cloud(_cloud(k * 100_000_000, frame='os_lidar'))
    assert len(pipeline.grid) == 0
    pipeline.add_cloud(_cloud(300_000_000, frame='os_lidar'))  # 0.3 s past the first
    assert len(pipeline.grid) == 1 and pipeline.counters['clouds'] == 4
    pipeline.add_cloud(_cloud(400_000_000, frame='os_lidar'))  # no more waiting
    assert len(pipeline.grid) == 1 and pipeline.counters['clouds'] == 5
    out = pipeline.detect()
    assert out.frame_id == 'os_lidar' and out.stamp_ns == 400_000_000
    np.testing.assert_allclose(out.lanes[0], _line(1.8), atol=1e-6)
    # nothing to count: there never was odometry to be without
    assert pipeline.counters['clouds_without_odometry'] == 0


def test_a_cloud_older_than_the_odometry_is_detected_alone_and_counted():
    # issue #17: such sweeps were dropped as bad clouds
    detector = FixedLanes([_line(1.8)], [0.9])
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), detector)
    pipeline.add_odometry(_odom(5_000_000_000, euler_to_matrix(7, 0, 0, 0, 0, 0)))
    pipeline.add_cloud(_cloud(4_500_000_000))
    assert pipeline.counters['clouds_without_odometry'] == 1
    out = pipeline.detect()
    assert (out.frame_id, out.stamp_ns) == ('lidar', 4_500_000_000)
    np.testing.assert_allclose(out.lanes[0], _line(1.8), atol=1e-6)
    pipeline.add_cloud(_cloud(5_000_000_000))  # covered: the odometry frame again, alone
    out = pipeline.detect()
    assert out.frame_id == 'odom' and len(pipeline.grid) == 1
    np.testing.assert_allclose(out.lanes[0], _line(1.8) + [7, 0, 0], atol=1e-6)


def test_a_cloud_ahead_of_its_odometry_waits_for_it():
    detector = FixedLanes([], [])
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), detector)
    pipeline.add_odometry(_odom(0, euler_to_matrix(0, 0, 0, 0, 0, 0)))
    pipeline.add_cloud(_cloud(100_000_000))  # its odometry is still on the way
    assert len(pipeline.grid) == 0 and pipeline.detect() is None
    pipeline.add_odometry(_odom(100_000_000, euler_to_matrix(2.0, 0, 0, 0, 0, 0)))
    assert len(pipeline.grid) == 1
    pipeline.detect()
    np.testing.assert_allclose(detector.windows[0].window_to_output[:3, 3], [2, 0, 0])
    # sweeps queue behind the odometry in stamp order, at most odom_wait_sec of stream time
    for k in (3, 2, 4, 5):
        pipeline.add_cloud(_cloud(k * 100_000_000))
    assert pipeline.waiting_stamps == [k * 100_000_000 for k in range(2, 6)]
    pipeline.add_odometry(_odom(300_000_000, euler_to_matrix(6.0, 0, 0, 0, 0, 0)))
    assert pipeline.waiting_stamps == [400_000_000, 500_000_000]
    assert pipeline.counters['clouds'] == 3 and pipeline.counters['sweeps_skipped'] == 0
    pipeline.add_cloud(_cloud(1_400_000_000))  # 1.0 s past the oldest waiting: it still waits
    assert pipeline.counters['clouds'] == 3
    pipeline.add_cloud(_cloud(1_500_000_000))  # more: the waiting ones go in alone, and
    # while odometry stays away a sweep waits only for a newer message
    assert pipeline.waiting_stamps == [1_500_000_000]
    assert pipeline.counters['clouds'] == 6 and pipeline.counters['clouds_without_odometry'] == 3
    pipeline.add_odometry(_odom(1_500_000_000, euler_to_matrix(9.0, 0, 0, 0, 0, 0)))
    assert not pipeline.waiting_stamps and pipeline.output_frame == 'odom'
    assert pipeline.counters['clouds_without_odometry'] == 3 and not pipeline.odometry_stopped
    assert pipeline.counters['odometry_timeouts'] == 1


def test_an_empty_cloud_frame_id_is_refused_and_changes_nothing():
    # issue #17: /lanes went out with frame_id '' for such clouds without odometry
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), FixedLanes([], []),
                            expect_odometry=False)
    with pytest.raises(ValueError, match='cloud has an empty frame_id'):
        pipeline.add_cloud(_cloud(100_000_000, frame=''))
    assert pipeline.counters['clouds'] == 0 and not pipeline.waiting_stamps
    assert pipeline.detect() is None
    pipeline.add_cloud(_cloud(200_000_000, frame='os_lidar'))
    assert pipeline.detect().frame_id == 'os_lidar'


def test_bad_odometry_is_refused_before_it_changes_anything():
    # NaN quaternions were accepted, then every cloud was refused against the NaN pose
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), FixedLanes([], []),
                            expect_odometry=False)
    nan = _odom(100_000_000, np.eye(4))
    nan.pose.pose.orientation.w = float('nan')
    empty = make_odometry(FAMILY, FAMILY.header(100_000_000, ''), 'lidar', np.eye(4))
    unit = _odom(100_000_000, np.eye(4))
    unit.pose.pose.orientation.w = 0.5
    for msg, message in ((nan, 'is not finite'), (empty, 'odometry has an empty frame_id'),
                         (unit, 'has norm 0.5, not 1')):
        with pytest.raises(ValueError, match=message):
            pipeline.add_odometry(msg)
    assert not pipeline.uses_odometry and pipeline.counters['odometry'] == 0
    pipeline.add_cloud(_cloud(100_000_000))  # per sweep, in the cloud frame
    out = pipeline.detect()
    assert out.frame_id == 'lidar' and np.isfinite(out.outline).all()


def test_max_points_bounds_the_clouds_the_pipeline_decodes():
    params = DetectorParams(size_px=64, resolution_m=0.5, max_points=200)
    pipeline = LanePipeline(params, FixedLanes([], []), expect_odometry=False)
    with pytest.raises(ValueError, match='201 points, more than max_points 200'):
        pipeline.add_cloud(_cloud(100_000_000, n=201))
    pipeline.add_cloud(_cloud(200_000_000, n=200))
    assert pipeline.counters['clouds'] == 1


def test_pose_buffer_extrapolates_the_newest_motion_a_bounded_way_ahead():
    buffer = PoseBuffer()
    assert buffer.extrapolated(100, 200_000_000) is None  # no poses
    for k in range(6):  # 10 m/s and 0.1 rad/s, poses every 20 ms
        t = k * 0.02
        buffer.add(k * 20_000_000, euler_to_matrix(10 * t, 0, 0, 0, 0, 0.1 * t))
    ahead = buffer.extrapolated(200_000_000, 200_000_000)
    # the motion of the newest pose and the one >= 50 ms before it (not of the last 20 ms)
    np.testing.assert_allclose(ahead[:3, 3], [2.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(np.arctan2(ahead[1, 0], ahead[0, 0]), 0.02, atol=1e-9)
    assert buffer.extrapolated(300_000_001, 200_000_000) is None  # past the reach
    # inside a gap too wide to interpolate: continued from the pose before it
    buffer.add(1_300_000_000, euler_to_matrix(13, 0, 0, 0, 0, 0.13))
    inside = buffer.extrapolated(200_000_000, 200_000_000)
    np.testing.assert_allclose(inside[:3, 3], [2.0, 0.0, 0.0], atol=0.01)
    lone = PoseBuffer()
    lone.add(0, np.eye(4))
    assert lone.extrapolated(50_000_000, 200_000_000) is None  # one pose: no motion known


def test_late_sweeps_go_in_extrapolated_up_to_the_reach_and_in_stamp_order():
    detector = FixedLanes([], [])
    params = DetectorParams(size_px=64, resolution_m=0.5, odom_extrapolate_sec=0.2)
    pipeline = LanePipeline(params, detector)
    for k in range(3):  # 20 m/s straight ahead, poses at 0, 0.1, 0.2 s
        pipeline.add_odometry(_odom(k * 100_000_000, euler_to_matrix(2.0 * k, 0, 0, 0, 0, 0)))
    for k in (3, 4, 5):  # their poses lost on the way
        pipeline.add_cloud(_cloud(k * 100_000_000))
    assert pipeline.waiting_stamps == [300_000_000, 400_000_000, 500_000_000]
    # the node's thread lets in those that waited too long: as far as the reach goes
    assert pipeline.extrapolate_waiting(500_000_000) == [300_000_000, 400_000_000]
    assert pipeline.waiting_stamps == [500_000_000]
    assert pipeline.counters['clouds_extrapolated'] == 2
    assert pipeline.counters['clouds_without_odometry'] == 0
    # the one let in behind a newer sweep first, in a window of its own (held back)
    assert [pipeline.detect().stamp_ns for _ in range(2)] == [300_000_000, 400_000_000]
    np.testing.assert_allclose(detector.windows[-1].window_to_output[:3, 3], [8, 0, 0])
    assert pipeline.output_frame == 'odom'
    # the next pose that comes covers the one left; the grid went on in the odometry frame
    pipeline.add_odometry(_odom(600_000_000, euler_to_matrix(12.0, 0, 0, 0, 0, 0)))
    assert not pipeline.waiting_stamps and len(pipeline.grid) == 3
    off = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5, odom_extrapolate_sec=0.0),
                       FixedLanes([], []))
    off.add_odometry(_odom(0, np.eye(4)))
    off.add_odometry(_odom(100_000_000, np.eye(4)))
    off.add_cloud(_cloud(200_000_000))
    assert off.extrapolate_waiting(200_000_000) == [] and off.waiting_stamps == [200_000_000]


def test_a_sweep_in_a_gap_too_wide_waits_for_the_late_poses_that_fill_it():
    # DDS lost the poses around it; the reliable reader gets them resent seconds later
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), FixedLanes([], []))
    for stamp in (0, 100_000_000):
        pipeline.add_odometry(_odom(stamp, euler_to_matrix(stamp * 2e-8, 0, 0, 0, 0, 0)))
    pipeline.add_cloud(_cloud(300_000_000))
    pipeline.add_odometry(_odom(1_300_000_000, euler_to_matrix(26, 0, 0, 0, 0, 0)))
    assert pipeline.waiting_stamps == [300_000_000]  # 1.2 s between the poses around it
    for stamp in (200_000_000, 400_000_000):  # resent
        pipeline.add_odometry(_odom(stamp, euler_to_matrix(stamp * 2e-8, 0, 0, 0, 0, 0)))
    assert not pipeline.waiting_stamps and pipeline.counters['clouds_without_odometry'] == 0
    pipeline.detect()
    np.testing.assert_allclose(pipeline.detector.windows[-1].window_to_output[:3, 3], [6, 0, 0])


def test_sweeps_held_back_by_their_odometry_get_windows_of_their_own():
    detector = FixedLanes([], [])
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), detector)
    pipeline.add_odometry(_odom(0, np.eye(4)))
    pipeline.add_cloud(_cloud(0))
    assert pipeline.detect().stamp_ns == 0
    for k in (1, 2, 3):  # their poses lost but the third's: it lets all three in at once
        pipeline.add_cloud(_cloud(k * 100_000_000))
    pipeline.add_odometry(_odom(300_000_000, euler_to_matrix(6.0, 0, 0, 0, 0, 0)))
    # oldest first (the held back ones are at most HELD_BACK_MAX: here both), then the newest
    stamps = [pipeline.detect().stamp_ns for _ in range(3)]
    assert stamps == [100_000_000, 200_000_000, 300_000_000]
    np.testing.assert_allclose(detector.windows[1].window_to_output[:3, 3], [2, 0, 0])
    assert detector.windows[1].stamp_ns == 100_000_000
    assert pipeline.detect() is None and pipeline.counters['sweeps_skipped'] == 0
    # one that is not due by rate_hz (the caller's due_ns) is passed over, and counted
    for k in (4, 5):
        pipeline.add_cloud(_cloud(k * 100_000_000))
    pipeline.add_odometry(_odom(500_000_000, euler_to_matrix(10.0, 0, 0, 0, 0, 0)))
    assert pipeline.take_window(due_ns=450_000_000).stamp_ns == 500_000_000
    assert pipeline.counters['sweeps_skipped'] == 1


def test_a_detection_is_due_at_rate_hz_on_the_sweep_stamps():
    params = DetectorParams(size_px=64, resolution_m=0.5, rate_hz=5.0)  # 180 ms apart at least
    pipeline = LanePipeline(params, FixedLanes([], []), expect_odometry=False)
    detected = []
    for k in range(7):  # 10 Hz sweeps: every other one is detected
        pipeline.add_cloud(_cloud(k * 100_000_000))
        out = pipeline.detect()
        detected += [] if out is None else [out.stamp_ns // 100_000_000]
    assert detected == [0, 2, 4, 6] and pipeline.counters['sweeps_skipped'] == 3
    assert pipeline.detect() is None  # nothing new
    pipeline.add_cloud(_cloud(50_000_000))  # time went back (a bag loop): due at once
    assert pipeline.detect().stamp_ns == 50_000_000


def test_bad_messages_are_dropped_and_counted_by_receive():
    pipeline = LanePipeline(DetectorParams(size_px=64, resolution_m=0.5), FixedLanes([], []))
    intake = pipeline.receive_cloud(_cloud(100_000_000, frame=''))
    assert 'empty frame_id' in str(intake.dropped) and intake.let_in == []
    bad_pose = _odom(0, np.eye(4))
    bad_pose.pose.pose.orientation.w = 0.0
    assert 'has norm 0' in str(pipeline.receive_odometry(bad_pose).dropped)
    assert pipeline.counters['bad_clouds'] == 1 and pipeline.counters['bad_odometry'] == 1
    assert pipeline.receive_odometry(_odom(0, np.eye(4))).dropped is None
    assert pipeline.receive_cloud(_cloud(0)).let_in == [0]
    assert pipeline.counters['clouds'] == 1
