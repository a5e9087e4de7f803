"""fhld_ros.evaluation.metrics on constructed cases: point metric, ONCE paper mode,
released-evaluator quirks, window clipping."""
from __future__ import annotations

import numpy as np
import pytest

from fhld_ros.evaluation import metrics as m
from fhld_ros.geometry import resample_polyline

HALF = 12.8


def straight(y: float, x0: float = -12.0, x1: float = 12.0, z: float = -1.8,
             n: int = 25) -> np.ndarray:
    x = np.linspace(x0, x1, n)
    return np.column_stack([x, np.full(n, y), np.full(n, z)])


def curved(y0: float, radius: float = 40.0) -> np.ndarray:
    x = np.linspace(-12.0, 12.0, 60)
    return np.column_stack([x, y0 + x**2 / (2 * radius), -1.8 + 0.02 * x])


LANES = [straight(y) for y in (-5.25, -1.75, 1.75)] + [curved(4.5)]


def shifted(lanes: list[np.ndarray], d: tuple[float, float, float]) -> list[np.ndarray]:
    return [lane + np.asarray(d) for lane in lanes]


# --- resampling and the point metric ------------------------------------------------------

def test_resample_spacing_and_ends() -> None:
    lane = curved(0.0)
    dense = resample_polyline(lane, m.SAMPLE_STEP)
    steps = np.linalg.norm(np.diff(dense, axis=0), axis=1)
    assert steps.max() <= m.SAMPLE_STEP + 1e-12
    np.testing.assert_allclose(dense[[0, -1]], lane[[0, -1]])
    assert len(resample_polyline(lane[:1], m.SAMPLE_STEP)) == 1
    # duplicate vertices do not break the arc-length interpolation
    assert np.isfinite(resample_polyline(np.repeat(lane, 2, axis=0), m.SAMPLE_STEP)).all()


def test_identical_lanes_score_100() -> None:
    scores = m.point_counts(LANES, LANES).scores()
    assert scores == {k: 100.0 for k in ('P@10', 'R@10', 'F1@10', 'P@30', 'R@30', 'F1@30')}


def test_5cm_lateral_shift_is_within_10cm() -> None:
    s = m.point_counts(shifted(LANES, (0, 0.05, 0)), LANES).scores()
    assert s['P@10'] == s['R@10'] == s['P@30'] == s['R@30'] == 100.0


def test_20cm_shift_fails_10cm_passes_30cm() -> None:
    s = m.point_counts([straight(y + 0.2) for y in (-5.25, -1.75, 1.75)],
                       [straight(y) for y in (-5.25, -1.75, 1.75)]).scores()
    assert s['P@10'] == s['R@10'] == s['F1@10'] == 0.0
    assert s['P@30'] == s['R@30'] == s['F1@30'] == 100.0


def test_distances_are_3d() -> None:
    s = m.point_counts(shifted(LANES, (0, 0, 0.2)), LANES).scores()
    assert s['P@10'] == 0.0 and s['P@30'] == 100.0


def test_missing_lane_lowers_recall_by_its_share_of_points() -> None:
    gt = [straight(-5.25), straight(-1.75, x0=-4.0), straight(1.75, x1=3.0), curved(4.5)]
    sizes = [len(resample_polyline(lane, m.SAMPLE_STEP)) for lane in gt]
    for missing in range(len(gt)):
        pred = gt[:missing] + gt[missing + 1:]
        s = m.point_counts(pred, gt).scores()
        expected = 100.0 * (1 - sizes[missing] / sum(sizes))
        assert s['R@10'] == pytest.approx(expected, abs=1e-9)
        assert s['R@30'] == pytest.approx(expected, abs=1e-9)
        assert s['P@10'] == 100.0


def test_counts_sum_over_frames() -> None:
    short, long = straight(0.0, -1.0, 1.0), straight(0.0)
    total = m.point_counts([short], [short]) + m.point_counts([], [long])
    n_short, n_long = (len(resample_polyline(x, m.SAMPLE_STEP)) for x in (short, long))
    assert total.n_gt == n_short + n_long
    # summed counts, not the mean of per-frame recalls (which would be 50)
    assert total.scores()['R@10'] == pytest.approx(100.0 * n_short / (n_short + n_long))
    assert total.scores()['P@10'] == 100.0


def test_empty_inputs() -> None:
    assert m.point_counts([], []).scores()['F1@10'] == 0.0
    s = m.point_counts(LANES, []).scores()
    assert s['P@10'] == 0.0 and s['R@10'] == 0.0


# --- window clipping ----------------------------------------------------------------------

def test_clip_cuts_at_window_edge_and_interpolates_z() -> None:
    lane = np.array([[-20.0, 0.0, 0.0], [20.0, 0.0, 4.0]])
    (piece,) = m.clip_polyline_to_square(lane, HALF)
    np.testing.assert_allclose(piece[:, 0], [-HALF, HALF])
    np.testing.assert_allclose(piece[:, 2], 2.0 + np.array([-HALF, HALF]) / 10.0)


def test_clip_splits_a_lane_that_leaves_and_returns() -> None:
    lane = np.array([[-10.0, 0.0, 0.0], [0.0, 20.0, 0.0], [10.0, 0.0, 0.0]])
    pieces = m.clip_polyline_to_square(lane, HALF)
    assert len(pieces) == 2
    for piece in pieces:
        assert np.all(np.abs(piece[:, :2]) <= HALF + 1e-9)
        assert np.isclose(np.abs(piece[:, 1]).max(), HALF)


def test_clip_keeps_inside_vertices_and_drops_outside_lanes() -> None:
    lane = curved(0.0)
    (piece,) = m.clip_polyline_to_square(lane, HALF)
    np.testing.assert_array_equal(piece, lane)
    assert m.clip_polyline_to_square(lane + [0, 30, 0], HALF) == []
    # touching the corner only is not a lane
    corner = np.array([[HALF - 1, HALF + 1, 0], [HALF + 1, HALF - 1, 0]])
    assert m.clip_polyline_to_square(corner, HALF) == []
    assert len(m.clip_lanes_to_square([lane, lane + [0, 30, 0]], HALF)) == 1


def test_clipped_gt_is_fully_recalled_by_inside_prediction() -> None:
    gt = m.clip_lanes_to_square([straight(1.75, -60, 60, n=7)], HALF)
    pred = m.clip_lanes_to_square([straight(1.75, -12.8, 12.8)], HALF)
    assert m.point_counts(pred, gt).scores()['R@10'] == 100.0
    # unclipped GT would count 120 m of lane against 25.6 m of window
    assert m.point_counts(pred, [straight(1.75, -60, 60)]).scores()['R@10'] < 25.0


# --- ONCE-3DLanes, paper definition -------------------------------------------------------

def test_once_identical_and_shifted() -> None:
    s = m.once_counts(LANES, LANES, HALF).scores()
    assert s == {'P': 100.0, 'R': 100.0, 'F1': 100.0, 'CD': 0.0}
    s = m.once_counts(shifted(LANES, (0, 0.2, 0)), LANES, HALF).scores()
    assert s['P'] == s['R'] == 100.0 and s['CD'] == pytest.approx(0.2, abs=5e-3)
    s = m.once_counts(shifted(LANES, (0, 0.4, 0)), LANES, HALF).scores()  # CD > 0.3 m
    assert s['P'] == s['R'] == 0.0


def test_once_missing_lane_and_false_positive() -> None:
    counts = m.once_counts(LANES[:3] + [straight(9.0)], LANES, HALF)
    assert (counts.n_pred, counts.n_gt, counts.tp) == (4, 4, 3)
    assert counts.scores()['F1'] == pytest.approx(75.0)


def test_once_paper_chamfer_is_3d() -> None:
    # same top view (IoU 1) but 40 cm higher: the 3D chamfer distance rejects it
    counts = m.once_counts(shifted(LANES, (0, 0, 0.4)), LANES, HALF)
    assert counts.tp == 0


def test_once_paper_applies_iou_threshold() -> None:
    gt = [straight(0.0, 2.0, 4.0, n=3)]  # 2 m of GT inside a 24 m prediction: CD 0, IoU ~0.16
    pred = [straight(0.0)]
    iou = m._iou_matrix([m.topview_mask(gt[0], HALF)], [m.topview_mask(pred[0], HALF)])
    assert iou[0, 0] < 0.3
    assert m.once_counts(pred, gt, HALF).tp == 0
    assert m.unilateral_chamfer(gt[0], pred[0]) < 0.01


def test_topview_mask_width() -> None:
    mask = m.topview_mask(straight(0.0), HALF)
    assert mask.shape == (512, 512)
    widths = mask.sum(axis=1)
    assert widths[256] == 30  # 1.5 m at 5 cm/px


# --- ONCE released evaluator: every documented quirk --------------------------------------

def test_camera_convention() -> None:
    cam = m.window_to_camera(np.array([[10.0, 2.0, -1.5]]))
    np.testing.assert_array_equal(cam, [[-2.0, 1.5, 10.0]])  # x right, y down, z forward


def test_official_identical_and_score_filter() -> None:
    counts = m.once_counts_official(LANES, [0.9] * 4, LANES)
    assert (counts.n_pred, counts.tp) == (4, 4)
    assert counts.scores()['P'] == 100.0 and counts.scores()['CD'] == pytest.approx(0.0)
    # score > t, strictly: a score equal to the threshold is dropped
    counts = m.once_counts_official(LANES, [0.9, 0.5, 0.5, 0.2], LANES, score_thresh=0.5)
    assert counts.n_pred == 1 and counts.n_gt == 4


def test_official_image_size_thickness_and_forward_cut() -> None:
    mask = m.official_mask(m.window_to_camera(straight(0.0, 0.0, 9.9, n=100)))
    assert mask.shape == (1000, 400)  # 50 m x 20 m at 5 cm/px
    rows = np.flatnonzero(mask.any(axis=1))
    assert mask[900].sum() == 31  # 30 px thick line (capsule radius 15 px)
    assert rows.min() >= 800 - 16  # nothing drawn beyond 10 m forward (+ half thickness)
    far = m.official_mask(m.window_to_camera(straight(0.0, 10.0, 12.0)))
    assert not far.any()  # every vertex at forward >= 10 m is dropped
    # lateral +-10 m image: a lane 10.5 m to the side is off the image
    assert not m.official_mask(m.window_to_camera(straight(10.8, 0.0, 9.0))).any()


def test_official_no_interpolation() -> None:
    sparse = np.array([[0.0, 0.0, -1.8], [20.0, 0.0, -1.8]])  # one vertex left below 10 m
    assert not m.official_mask(m.window_to_camera(sparse)).any()
    dense = resample_polyline(sparse, 1.0)
    assert m.official_mask(m.window_to_camera(dense)).any()


def test_official_truncates_pixel_indices_toward_zero() -> None:
    def centre_col(y: float) -> float:
        mask = m.official_mask(m.window_to_camera(straight(y, 1.0, 9.0)))
        return float(np.flatnonzero(mask[900]).mean())
    assert centre_col(-0.07) == 201  # x_cam = 0.07 -> 1.4 px -> 1
    assert centre_col(0.07) == 199  # x_cam = -0.07 -> -1.4 px -> -1 (floor would give -2)


def test_official_ignores_iou_threshold_and_forward_axis() -> None:
    gt = [straight(0.0, 2.0, 8.0)]
    behind = [straight(0.2, -12.0, -5.0)]  # 20 cm to the side, entirely behind the ego
    iou = m._iou_matrix([m.official_mask(m.window_to_camera(gt[0]))],
                        [m.official_mask(m.window_to_camera(behind[0]))])
    assert iou[0, 0] == 0.0
    official = m.once_counts_official(behind, [1.0], gt)
    assert official.tp == 1 and official.cd_sum == pytest.approx(0.2)
    assert m.once_counts(behind, gt, HALF).tp == 0  # the paper's metric rejects it
    # 2 m GT inside a long prediction: IoU < 0.3 but matched anyway
    assert m.once_counts_official([straight(0.0)], [1.0], [straight(0.0, 2.0, 4.0, n=3)]).tp == 1


def test_official_chamfer_samples_in_the_lateral_height_plane() -> None:
    # 5 m straight ahead, then 1 m to the right over the next 5 m: in the (x_cam, y_cam) plane
    # only the second part has length, so the 10 samples lie at x_cam = 0.05 ... 0.95
    gt = m.window_to_camera(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, -1.0, 0.0]]))
    pred = m.window_to_camera(straight(0.0, 0.0, 10.0, z=0.0))
    assert m.official_chamfer(gt, pred) == pytest.approx(0.5)
    # height offsets count (y_cam), forward offsets do not (z_cam)
    lane = straight(0.0, 0.0, 9.0)
    assert m.official_chamfer(m.window_to_camera(lane),
                              m.window_to_camera(lane + [5.0, 0.0, 0.1])) == pytest.approx(0.1)


def test_official_strict_cd_threshold_and_normalisation() -> None:
    gt = [straight(0.0, 1.0, 9.0)]
    pred = [straight(0.25, 1.0, 9.0)]  # every distance is exactly 0.25 m
    assert m.once_counts_official(pred, [1.0], gt, cd_thresh=0.25).tp == 0  # CD < t
    assert m.once_counts(pred, gt, HALF, cd_thresh=0.25).tp == 1  # paper: CD <= t
    counts = m.once_counts_official(pred, [1.0], gt)
    assert counts.tp == 1 and counts.cd_sum == 0.25
    # mean CD divides by TP + 1e-5 like the released summary
    assert counts.scores()['CD'] == 0.25 / (1 + 1e-5)
    assert m.once_counts(pred, gt, HALF).scores()['CD'] == 0.25


def test_official_point_count_rules() -> None:
    gt = [straight(0.0, 1.0, 9.0), straight(3.5, 1.0, 9.0), np.array([[1.0, 7.0, -1.8]])]
    pred = [straight(0.05, 1.0, 9.0), np.array([[5.0, 3.5, -1.8]])]
    counts = m.once_counts_official(pred, [1.0] * 2, gt)
    assert counts.n_gt == 2  # a one-point GT lane is dropped ...
    assert counts.n_pred == 2  # ... a one-point prediction is not
    # the lone point draws nothing (IoU 0) but lies on GT lane 2 in the lateral/height plane
    assert counts.tp == 2
    with pytest.raises(ValueError):
        m.once_counts_official(pred, [1.0], gt)
