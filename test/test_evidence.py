"""fhld_ros.evidence: lanes are cut where no observed cell lies within reach, and dropped
where no paint shows."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fhld_ros.bev import MIN_HEIGHT_HIGH_M, MIN_HEIGHT_LOW_M
from fhld_ros.detectors import evidence_checked
from fhld_ros.evidence import (
    _observed_count,
    _quantile,
    _row_prefix,
    keep_observed,
    keep_painted,
    paint_contrast,
    stripe_contrast,
)
from fhld_ros.parameters import DetectorParams

RES = 0.04
SIZE = 640
HALF = SIZE * RES / 2


def raster_observed(x_from: float, x_to: float) -> np.ndarray:
    """A raster whose density is non-zero for window x in [x_from, x_to) only."""
    raster = np.zeros((4, SIZE, SIZE), dtype=np.float32)
    c0, c1 = (int((x + HALF) / RES) for x in (x_from, x_to))
    raster[1, :, c0:c1] = 0.5
    return raster


def straight_lane(x0: float = -12.0, x1: float = 12.0, y: float = 1.75) -> np.ndarray:
    x = np.linspace(x0, x1, 49)
    return np.column_stack([x, np.full_like(x, y), np.full_like(x, -1.8)])


def test_observed_counts_match_a_brute_force_dilation():
    rng = np.random.default_rng(0)
    raster = np.zeros((4, 48, 48), dtype=np.float32)
    raster[1][rng.random((48, 48)) < 0.01] = 1.0
    occupied = np.argwhere(raster[1] > 0)
    rows, cols = np.mgrid[:48, :48]
    for reach in (0, 1, 3, 50):
        expected = np.zeros((48, 48), dtype=bool)
        for r, c in occupied:
            expected |= (np.abs(rows - r) <= reach) & (np.abs(cols - c) <= reach)
        counts = _observed_count(_row_prefix(raster), rows, cols, reach).reshape(rows.shape)
        np.testing.assert_array_equal(counts > 0, expected)


def test_a_lane_ends_where_the_observed_ground_ends():
    lanes, conf = keep_observed([straight_lane()], np.array([0.9]), raster_observed(0.0, 12.8),
                                RES, reach_m=1.0)
    assert len(lanes) == 1
    np.testing.assert_allclose(conf, [0.9])
    assert lanes[0][:, 0].min() >= -1.0 - 0.5  # reach 1 m plus one lane-point spacing
    assert lanes[0][:, 0].max() == 12.0


def test_gaps_inside_a_lane_stay_bridged_and_short_spans_go():
    # observed at both ends, a 4 m unobserved gap in the middle (a row of cars, the blind ring
    # of a single sweep): one lane, whole
    raster = raster_observed(-12.8, 12.8)
    c0, c1 = (int((x + HALF) / RES) for x in (-2.0, 2.0))
    raster[1, :, c0:c1] = 0.0
    lanes, conf = keep_observed([straight_lane()], np.array([0.8]), raster, RES, reach_m=0.5)
    assert len(lanes) == 1 and len(lanes[0]) == 49
    np.testing.assert_allclose(conf, [0.8])
    # a supported span shorter than min_length is dropped with its lane
    lanes, conf = keep_observed([straight_lane()], np.array([0.8]), raster_observed(11.0, 12.8),
                                RES, reach_m=0.1, min_length_m=2.0)
    assert lanes == [] and conf.size == 0
    # a lane crossing a 2 m observed strip keeps that span (plus the reach), nothing beyond
    lanes, _ = keep_observed([straight_lane(y=8.0)], np.array([0.8]), raster_observed(-1, 1),
                             RES, reach_m=1.0)
    assert len(lanes) == 1 and np.abs(lanes[0][:, 0]).max() <= 2.0 + 0.5
    # over ground nobody saw at all, no lane
    nothing = np.zeros((4, SIZE, SIZE), dtype=np.float32)
    assert keep_observed([straight_lane()], np.array([0.8]), nothing, RES, 1.5)[0] == []


def test_reach_zero_or_no_lanes_change_nothing():
    lane = straight_lane()
    lanes, conf = keep_observed([lane], np.array([0.7]), raster_observed(0, 1), RES, reach_m=0)
    assert lanes[0] is lane and conf.tolist() == [0.7]
    assert keep_observed([], np.zeros(0), raster_observed(0, 1), RES, 1.0)[0] == []


# paint evidence: a road of mean intensity ROAD at height ROAD_Z, observed everywhere
ROAD, ROAD_Z = 0.05, -1.8


def road_raster() -> np.ndarray:
    raster = np.zeros((4, SIZE, SIZE), dtype=np.float32)
    raster[0] = ROAD
    raster[1] = 0.5
    raster[3] = (ROAD_Z - MIN_HEIGHT_LOW_M) / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M)
    return raster


def rows_between(y0: float, y1: float) -> slice:
    """Raster rows of window y in [y0, y1)."""
    return slice(int(np.floor((y0 + HALF) / RES)), int(np.floor((y1 + HALF) / RES)))


def test_a_painted_line_keeps_its_lane_and_plain_road_does_not():
    raster = road_raster()
    raster[0, rows_between(1.68, 1.84)] = 2 * ROAD  # a line twice as bright as the road
    painted, plain = straight_lane(y=1.75), straight_lane(y=-1.75)
    assert paint_contrast(painted, raster, RES) == pytest.approx(2.0)
    assert paint_contrast(plain, raster, RES) == pytest.approx(1.0)
    lanes, conf = keep_painted([painted, plain], np.array([0.9, 0.99]), raster, RES, 1.3)
    assert len(lanes) == 1 and lanes[0] is painted and conf.tolist() == [0.9]
    # a ratio: the sensor's units and gain do not change it
    raster[0] *= 7.0
    assert paint_contrast(painted, raster, RES) == pytest.approx(2.0)


def test_the_served_check_counts_the_lanes_without_paint_it_drops():
    raster = road_raster()
    raster[0, rows_between(1.68, 1.84)] = 2 * ROAD
    window = SimpleNamespace(raster=raster, spec=SimpleNamespace(resolution_m=RES))
    lanes = [straight_lane(y=1.75), straight_lane(y=-1.75), straight_lane(y=-5.25)]
    params = DetectorParams(min_paint_contrast=1.3)
    kept, conf, unpainted = evidence_checked(lanes, np.array([0.9, 0.8, 0.7]), window, params)
    assert len(kept) == 1 and conf.tolist() == [0.9] and unpainted == 2
    params = DetectorParams(min_paint_contrast=0.0)  # the check off: nothing dropped
    assert evidence_checked(lanes, np.array([0.9, 0.8, 0.7]), window, params)[2] == 0


def test_dashes_are_paint():
    raster = road_raster()
    dashes = rows_between(1.68, 1.84), (np.arange(SIZE) * RES) % 12.0 < 3.0  # 3 m every 12 m
    raster[0][dashes[0], dashes[1]] = 1.6 * ROAD
    assert paint_contrast(straight_lane(y=1.75), raster, RES) == pytest.approx(1.6)


def strip_and_band(strip: tuple[float, float], strip_gain: float, band: tuple[float, float],
                   band_gain: float) -> tuple[np.ndarray, np.ndarray]:
    """The road with a strip and a band (window y from, to) that many times as bright, and a
    lane along y = 5 m."""
    raster = road_raster()
    raster[0, rows_between(*strip)] = strip_gain * ROAD
    raster[0, rows_between(*band)] = band_gain * ROAD
    return raster, straight_lane(y=5.0)


def test_a_strip_darker_than_the_road_on_one_side_is_no_line():
    # a strip 1.5 x the road along a band twice as bright at the road's height (a concrete
    # gutter, a light verge): brighter than one side only
    raster, lane = strip_and_band((4.84, 5.2), 1.5, (5.2, 6.5), 2.0)
    assert paint_contrast(lane, raster, RES) == pytest.approx(0.75)
    assert stripe_contrast(lane, raster, RES) == pytest.approx(0.75)  # an edge, not a stripe
    assert keep_painted([lane], np.array([0.98]), raster, RES, 1.3)[0] == []
    # the same band raised 0.15 m (a sidewalk behind a curb) is not road: the strip stands out
    # from the road on the other side
    raster[3, rows_between(5.2, 6.5)] += 0.15 / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M)
    assert paint_contrast(lane, raster, RES) == pytest.approx(1.5)


def test_a_worn_line_inside_a_light_verge_is_a_stripe():
    # worn paint 1.8 x the road, asphalt for 0.4 m beyond it, then a verge 2.5 x the road at the
    # road's height: dimmer than the verge 0.35-1 m away, but a stripe against the road right
    # beside it on both sides
    raster, lane = strip_and_band((4.92, 5.08), 1.8, (5.5, 6.5), 2.5)
    assert paint_contrast(lane, raster, RES) == pytest.approx(0.72)
    assert stripe_contrast(lane, raster, RES) == pytest.approx(1.8)
    assert len(keep_painted([lane], np.array([0.9]), raster, RES, 1.3)[0]) == 1
    # a stripe must stand out more than a line against the wider road: 1.5 x is not enough
    raster[0, rows_between(4.92, 5.08)] = 1.5 * ROAD
    assert keep_painted([lane], np.array([0.9]), raster, RES, 1.3)[0] == []
    # with the road right beside it unobserved on one side there is no stripe to see
    raster[0, rows_between(4.92, 5.08)] = 1.8 * ROAD
    raster[1, rows_between(4.65, 4.85)] = 0.0
    assert np.isnan(stripe_contrast(lane, raster, RES))
    assert keep_painted([lane], np.array([0.9]), raster, RES, 1.3)[0] == []


def test_without_evidence_either_way_a_lane_stays():
    raster = road_raster()
    raster[1, rows_between(-3.0, 3.0)] = 0.0  # nothing observed on or beside the lane
    lane = straight_lane(y=0.0)
    assert np.isnan(paint_contrast(lane, raster, RES))
    assert len(keep_painted([lane], np.array([0.8]), raster, RES, 1.3)[0]) == 1
    assert np.isnan(paint_contrast(lane[:1], road_raster(), RES))  # a single point


def test_min_contrast_zero_or_no_lanes_change_nothing():
    lane = straight_lane(y=-1.75)
    lanes, conf = keep_painted([lane], np.array([0.7]), road_raster(), RES, 0.0)
    assert lanes[0] is lane and conf.tolist() == [0.7]
    assert keep_painted([], np.zeros(0), road_raster(), RES, 1.3)[0] == []


@pytest.mark.parametrize('size', [1, 2, 7, 10, 501])
@pytest.mark.parametrize('q', [0.0, 0.5, 0.95, 1.0])
def test_partition_quantile_is_numpys(size, q):
    values = np.random.default_rng(size).gamma(2.0, size=size).astype(np.float32)
    assert _quantile(values, q) == pytest.approx(float(np.quantile(values, q)), rel=1e-6)
