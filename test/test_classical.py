"""Classical baseline on synthetic windows: flat (sloped) road, bright stripes, distractors."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fhld_ros.classical import ClassicalConfig, ClassicalLaneDetector, otsu_threshold
from fhld_ros.evaluation.metrics import SAMPLE_STEP, point_counts
from fhld_ros.geometry import resample_polyline

HALF = 12.8


def ground_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return -1.8 + 0.03 * x - 0.02 * y  # sloped road, heights relative to the sensor


def gt_lanes() -> dict[str, np.ndarray]:
    x = np.linspace(-HALF, HALF, 257)
    ys = {'solid': np.full_like(x, 1.75), 'dashed': np.full_like(x, -1.75),
          'curved': 4.5 + x**2 / 80.0}
    return {k: np.column_stack([x, y, ground_z(x, y)]) for k, y in ys.items()}


def scene(seed: int = 0, n: int = 200_000, markings: bool = True,
          gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Road with 15 cm stripes, an arrow-like blob, a crosswalk, a bright car and a guard rail."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-HALF, HALF, (2, n))
    z = ground_z(x, y) + rng.normal(0.0, 0.01, n)
    inten = rng.uniform(0.05, 0.25, n)
    if markings:
        solid = np.abs(y - 1.75) < 0.075
        dashed = (np.abs(y + 1.75) < 0.075) & (np.mod(x + HALF, 9.0) < 3.0)
        curved = np.abs(y - (4.5 + x**2 / 80.0)) < 0.075
        blob = (np.abs(x - 5.0) < 0.8) & (np.abs(y + 6.0) < 0.8)
        bars = (x > -11.0) & (x < -8.0) & (y > -12.0) & (y < -6.0) & (np.mod(y, 1.0) < 0.5)
        bright = solid | dashed | curved | blob | bars
        inten[bright] = rng.uniform(0.6, 0.9, bright.sum())
    m = n // 10  # a car: 1.5 m of bright-ish points above the road
    car = np.column_stack([rng.uniform(-8, -4, m), rng.uniform(-5.5, -4.0, m),
                           rng.uniform(-1.5, 0.0, m)])
    k = n // 50  # a guard rail with a reflective strip 0.6 m above the road: long and thin
    rail_x, rail_y = rng.uniform(-HALF, HALF, k), rng.uniform(11.45, 11.55, k)
    rail = np.column_stack([rail_x, rail_y, ground_z(rail_x, rail_y) + 0.6])
    points = np.concatenate([np.column_stack([x, y, z]), car, rail]).astype(np.float32)
    intensity = np.concatenate([inten, rng.uniform(0.5, 1.0, m), np.full(k, 0.8)]) * gain
    return points, intensity.astype(np.float32)


def match(lanes: list[np.ndarray]) -> dict[str, tuple[float, float]]:
    """GT name -> (mean, max) distance of the detected lane closest to it."""
    out = {}
    for name, gt in gt_lanes().items():
        tree = cKDTree(resample_polyline(gt, SAMPLE_STEP))
        dists = [tree.query(resample_polyline(lane, SAMPLE_STEP))[0] for lane in lanes]
        best = min(dists, key=np.mean)
        out[name] = (float(best.mean()), float(best.max()))
    return out


@pytest.fixture(scope='module')
def detected() -> tuple[list[np.ndarray], np.ndarray]:
    return ClassicalLaneDetector().detect(*scene())


def test_finds_the_three_lanes_within_centimetres(detected) -> None:
    lanes, confs = detected
    assert len(lanes) == 3  # blob, crosswalk, car and rail rejected
    for name, (mean, worst) in match(lanes).items():
        assert mean < 0.03 and worst < 0.08, name
    for lane in lanes:
        assert lane.dtype == np.float64 and lane.ndim == 2 and lane.shape[1] == 3
    assert np.all((confs > 0) & (confs <= 1)) and np.all(np.diff(confs) <= 0)


def test_lanes_cover_the_markings(detected) -> None:
    lanes, _ = detected
    gt = gt_lanes()
    scores = point_counts(lanes, [gt['solid'], gt['curved']]).scores()
    assert scores['R@10'] > 95.0
    # the dashed lane spans its dashes (and the gaps between), not beyond the last one
    dashed = min(lanes, key=lambda lane: np.abs(lane[:, 1] + 1.75).mean())
    assert dashed[:, 0].min() < -12.0 and 8.0 < dashed[:, 0].max() < 8.4
    # heights follow the sloped road
    for lane in lanes:
        np.testing.assert_allclose(lane[:, 2], ground_z(lane[:, 0], lane[:, 1]), atol=0.03)


def test_threshold_adapts_to_a_dim_sweep() -> None:
    lanes, _ = ClassicalLaneDetector().detect(*scene(seed=1, gain=0.4))
    assert len(lanes) == 3
    assert all(mean < 0.03 for mean, _ in match(lanes).values())


def test_no_markings_no_lanes() -> None:
    lanes, confs = ClassicalLaneDetector().detect(*scene(seed=2, markings=False))
    assert lanes == [] and confs.shape == (0,)


def test_degenerate_input() -> None:
    det = ClassicalLaneDetector()
    assert det.detect(np.zeros((0, 3), np.float32), np.zeros(0, np.float32))[0] == []
    points, inten = scene(n=5000)
    points[::7] = np.nan
    det.detect(points, inten)  # NaNs are dropped, not propagated
    with pytest.raises(ValueError):
        det.detect(points, inten[:-1])


def test_config_is_frozen_and_used() -> None:
    cfg = ClassicalConfig()
    with pytest.raises(AttributeError):
        cfg.max_width_m = 2.0  # type: ignore[misc]
    strict = ClassicalLaneDetector(ClassicalConfig(min_lane_length_m=30.0))
    assert strict.detect(*scene(n=50_000))[0] == []


def test_otsu_splits_two_modes() -> None:
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.uniform(0.1, 0.2, 900), rng.uniform(0.7, 0.8, 100)])
    thresh, contrast = otsu_threshold(values)
    assert 0.2 <= thresh <= 0.7 and contrast == pytest.approx(0.6, abs=0.02)


def test_detect_window_returns_output_frame(detected) -> None:
    T = np.eye(4)
    T[:3, 3] = [100.0, -50.0, 2.0]
    points, inten = scene()
    window = SimpleNamespace(points_window=points, intensity=inten,
                             to_output=lambda p: np.asarray(p) @ T[:3, :3].T + T[:3, 3])
    lanes, confs = ClassicalLaneDetector().detect_window(window)
    np.testing.assert_allclose(lanes[0], detected[0][0] + T[:3, 3])
    np.testing.assert_allclose(confs, detected[1])
