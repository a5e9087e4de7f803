"""Real development sweeps (../shared/real_scans): hand labels, scoring, the shipped weights.

The sweeps are not part of the repository (KITTI's licence forbids it): the tests that read
them skip when the folder is absent (needs_scans); those on constructed sweeps always run.
Labels: docs/real_scan_labels.json, made as docs/real_scans.md says.
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from fhld_ros.errors import ConfigError
from fhld_ros.evaluation import real_scan_diagnosis, real_scans
from fhld_ros.evaluation.real_scans import LabelledLine, ScanLabels, score_scan
from fhld_ros.intensity_rings import elevation_ring_ids
from fhld_ros.parameters import DetectorParams

needs_scans = pytest.mark.skipif(not real_scans.DEFAULT_DIR.is_dir(),
                                 reason=f'{real_scans.DEFAULT_DIR} is absent')

NO_PAINT = 'kitti_city_nopaint_09.bin'
# The floor and ceiling below hold for these eight sweeps (KITTI HDL-64E and Hesai 64). The
# nuScenes HDL-32E sweeps labelled later are new development data, scored separately
# (docs/real_scans.md): the shipped weights were chosen without them, so they are reported,
# not held to this floor.
FLOOR_SCANS = (
    'kitti_training_000001.bin', 'kitti_training_000005.bin', 'kitti_testing_000001.bin',
    'kitti_testing_000004.bin', NO_PAINT, 'pjlab_lidar2camera_manual_0.bin',
    'pjlab_lidar2lidar_p64.bin', 'pjlab_lidar2camera_auto_calib.bin')
# lines the shipped weights find on FLOOR_SCANS at every gain: 18 of 18 (`fhld realscans`),
# 1 of 20 published lanes false (docs/real_scans.md); the floor and ceiling sit a little
# beyond, so that losing lines or gaining false lanes fails
FHLD_FOUND_FLOOR = 17
FHLD_FALSE_CEILING = 0.06
# "bright" in the paint check is this many times the road beside the line (default 1.3). The
# accumulated nuScenes sweep's road has two surfaces: right of its line ~2 x as bright as left
# of it (paint 3-5 x), so 1.3 x their pooled median counts the brighter asphalt as paint too
BRIGHT_OVER_ROAD = {'nuscenes_10sweeps_ff9eff.fp16x5.bin': 2.0}


@pytest.fixture(scope='module')
def labels() -> list[ScanLabels]:
    return real_scans.load_labels()


@needs_scans
def test_label_file_is_well_formed(labels: list[ScanLabels]) -> None:
    document = json.loads(real_scans.LABELS.read_text())
    assert {scan['file'] for scan in document['scans']} == {
        path.name for path in real_scans.DEFAULT_DIR.glob('*.bin')}
    assert sum(len(scan.lines) for scan in labels) >= 15
    for scan in labels:
        assert scan.sensor and scan.notes, scan.file
        assert (scan.file == NO_PAINT) == (not scan.lines)
        points = xyzi(real_scans.DEFAULT_DIR / scan.file)
        for line in scan.lines:
            p = line.points
            assert (np.abs(p[:, :2]) <= 12.8 + 1e-6).all(), (scan.file, line.id)
            assert np.all(np.diff(p[:, 0]) > 0), 'these roads run along x: vertices in x order'
            assert np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).max() <= 1.5
            # z on the road: at every vertex with returns within 0.5 m (none in the blind ring;
            # those within 3.5 m of the sensor hit the car itself) the lowest is the label's z;
            # the second lowest, since one stray return may lie below the road (nuscenes_n008
            # has one 0.42 m under its paint at x = 3.9 m, intensity 0: a multipath ghost)
            near = np.linalg.norm(points[None, :, :2] - p[:, None, :2], axis=2) < 0.5
            seen = (near.sum(axis=1) >= 3) & (np.hypot(p[:, 0], p[:, 1]) > 3.5)
            lowest = np.array([np.partition(points[mask, 2], 1)[1] for mask in near[seen]])
            assert np.abs(p[seen, 2] - lowest).max() < 0.15, (scan.file, line.id)


def xyzi(path) -> np.ndarray:
    """(N, 4) float32 x y z intensity of a sweep in the sensor frame, read as the scorer does."""
    sweep = real_scans.read_sweep(path)
    return np.column_stack([sweep[n] for n in ('x', 'y', 'z', 'intensity')]).astype('<f4')


def _bright_share(points: np.ndarray, line: np.ndarray, shift: float,
                  factor: float = 1.3) -> tuple[float, float]:
    """Share of bright ground returns on the line (within 0.12 m) and beside it (0.5-1 m).

    The line is moved `shift` metres sideways; bright = above `factor` x the median intensity
    of the road beside it. Lines run along x, so the lateral offset is y - line_y(x).
    """
    lx, ly, lz = line[:, 0], line[:, 1] + shift, line[:, 2]
    inside = (points[:, 0] >= lx[0]) & (points[:, 0] <= lx[-1])
    x, y, z, intensity = points[inside].T
    offset = np.abs(y - np.interp(x, lx, ly))
    ground = np.abs(z - np.interp(x, lx, lz)) < 0.2
    on, side = ground & (offset < 0.12), ground & (offset > 0.5) & (offset < 1.0)
    bright = intensity > factor * np.median(intensity[side])
    return float(bright[on].mean()), float(bright[side].mean())


def _on_paint(points: np.ndarray, line: np.ndarray, shift: float = 0.0,
              factor: float = 1.3) -> bool:
    """The line runs over paint: many bright returns, more than beside it and than 0.3 m off."""
    on, side = _bright_share(points, line, shift, factor)
    nearby = max(_bright_share(points, line, shift + d, factor)[0] for d in (-0.3, 0.3))
    return on >= 0.25 and on >= 1.5 * side and on >= nearby


@needs_scans
def test_every_labelled_line_lies_on_bright_ground_points(labels: list[ScanLabels]) -> None:
    for scan in labels:
        points = xyzi(real_scans.DEFAULT_DIR / scan.file).astype(np.float64)
        factor = BRIGHT_OVER_ROAD.get(scan.file, 1.3)
        for line in scan.lines:
            assert _on_paint(points, line.points, 0.0, factor), (scan.file, line.id)
            # the check can fail: the same line 1 m to either side is not on paint
            for shift in (-1.0, 1.0):
                assert not _on_paint(points, line.points, shift, factor), (
                    scan.file, line.id, shift)


def _straight(y: float, x0: float = -12.8, x1: float = 12.8, z: float = -1.7) -> np.ndarray:
    x = np.linspace(x0, x1, 27)
    return np.stack([x, np.full_like(x, y), np.full_like(x, z)], axis=1)


def test_scoring_on_constructed_cases() -> None:
    scan = ScanLabels('made.bin', 'none', (LabelledLine('a', 'solid', _straight(-1.75)),
                                           LabelledLine('b', 'dashed', _straight(1.75)),
                                           LabelledLine('c', 'solid', _straight(5.25))))
    lanes = [
        _straight(-1.55),  # 0.2 m off line a over its length: a found, lane true
        _straight(1.75, -12.8, -2.6),  # 40 % of line b: b missed, lane true (all on b)
        _straight(1.75, -12.8, 3.0) + [0, 0.25, 0],  # 0.25 m off b over 62 %: b found
        _straight(8.75),  # on no labelled line: false
        _straight(5.0, -40.0, 40.0),  # 0.25 m off c; the parts outside the window don't count
    ]
    score = score_scan(scan, lanes, half=12.8)
    assert score.line_cover['a'] == 1.0 and score.line_cover['c'] == 1.0
    assert score.line_cover['b'] == pytest.approx(0.62, abs=0.02)
    assert (score.found, score.false) == (3, 1)
    assert score.lane_cover == [1.0, 1.0, 1.0, 0.0, 1.0]
    assert (score_scan(scan, lanes[1:2]).found, score_scan(scan, lanes[1:2]).false) == (0, 0)
    # 0.35 m away is not on the line; nothing published: nothing found, nothing false
    far = score_scan(scan, [_straight(-1.75 + 0.35)])
    assert (far.found, far.false) == (0, 1)
    assert (score_scan(scan, []).found, score_scan(scan, []).false) == (0, 0)
    no_paint = score_scan(ScanLabels('none.bin', 'none', ()), [_straight(0.0), _straight(3.0)])
    assert (no_paint.found, no_paint.false, len(no_paint.lane_cover)) == (0, 2, 2)
    totals = real_scans.totals([score, no_paint])['1']
    assert totals['all'] == {'labelled': 3, 'found': 3, 'published': 7, 'false': 3}


def test_distance_to_polylines_measures_to_segments() -> None:
    line = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    points = np.array([[5.0, 0.3], [-3.0, 4.0], [12.0, 0.0]])
    assert np.allclose(real_scans.distance_to_polylines(points, [line]), [0.3, 5.0, 2.0])
    assert np.isinf(real_scans.distance_to_polylines(points, [])).all()


def test_read_sweep_layouts_by_name(tmp_path) -> None:
    # nuScenes LIDAR_TOP (x right, y forward): a point 2 m right, 5 m ahead -> x 5, y -2
    row = [2.0, 5.0, -1.8, 40.0, 7.0]
    (tmp_path / 'one.pcd.bin').write_bytes(np.array([row], '<f4').tobytes())
    (tmp_path / 'acc.fp16x5.bin').write_bytes(np.array([row], '<f2').tobytes())
    (tmp_path / 'kitti.bin').write_bytes(np.array([row[:4]], '<f4').tobytes())
    one = real_scans.read_sweep(tmp_path / 'one.pcd.bin')
    acc = real_scans.read_sweep(tmp_path / 'acc.fp16x5.bin')
    kitti = real_scans.read_sweep(tmp_path / 'kitti.bin')
    assert one.dtype.names == ('x', 'y', 'z', 'intensity', 'ring')
    assert acc.dtype.names == ('x', 'y', 'z', 'intensity', 'dt')
    for sweep in (one, acc):  # float16 keeps -1.8 to 1e-3
        packed = real_scans.cloud_points(sweep)
        assert np.allclose([packed[n][0] for n in ('x', 'y', 'z', 'intensity')],
                           [5, -2, -1.8, 40], atol=1e-3)
    assert one['ring'][0] == 7.0 and acc['dt'][0] == 7.0
    # the cloud a driver sends: the ring as uint16 where the file has one, no dt
    assert real_scans.cloud_points(one).dtype.names == ('x', 'y', 'z', 'intensity', 'ring')
    assert real_scans.cloud_points(acc).dtype.names == ('x', 'y', 'z', 'intensity')
    assert np.allclose(kitti.view('<f4'), [2, 5, -1.8, 40])  # KITTI: already x forward
    (tmp_path / 'bad.pcd.bin').write_bytes(b'\0' * 24)
    with pytest.raises(ConfigError, match='not a multiple of 20'):
        real_scans.read_sweep(tmp_path / 'bad.pcd.bin')


def test_bad_input_is_one_clear_error(tmp_path) -> None:
    (tmp_path / NO_PAINT).write_bytes(b'\0' * 10)  # not whole 16-byte points
    with pytest.raises(ConfigError, match='not a multiple of 16'):
        real_scans.evaluate(tmp_path, DetectorParams(detector='classical'))
    with pytest.raises(ConfigError, match='none of the labelled scans'):
        real_scans.evaluate(tmp_path / 'missing', DetectorParams(detector='classical'))
    bad_labels = tmp_path / 'labels.json'
    bad_labels.write_text('{"scans": [{"file": "x.bin", "lines": [{"id": "a"}]}]}')
    with pytest.raises(ConfigError, match='cannot read labels'):
        real_scans.evaluate(real_scans.DEFAULT_DIR, DetectorParams(), labels_path=bad_labels)


def _command(argv: list[str], capsys: pytest.CaptureFixture) -> tuple[str, dict]:
    parser = argparse.ArgumentParser()
    real_scans.add_arguments(parser)
    assert real_scans.run(parser.parse_args(argv)) == 0
    out = capsys.readouterr().out
    return out, json.loads(out.strip().splitlines()[-1])


@needs_scans
def test_command_classical_all_gains(capsys: pytest.CaptureFixture) -> None:
    out, result = _command(['--detector', 'classical', '--json'], capsys)
    assert result['detector'] == 'classical' and set(result['totals']) == {'1', '0.5', '2'}
    labels = real_scans.load_labels()
    assert len(result['scans']) == 3 * len(labels)
    assert 'total gain    1 all' in out
    assert result['totals']['1']['all']['labelled'] == sum(len(scan.lines) for scan in labels)


@needs_scans
def test_shipped_weights_on_the_real_scans(capsys: pytest.CaptureFixture) -> None:
    out, result = _command([str(real_scans.DEFAULT_DIR), '--gains', '1', '4', '--json'],
                           capsys)
    for scan in result['scans']:
        if scan['file'] == NO_PAINT:
            assert scan['published'] == 0, 'lanes on a road without paint'
    floor = real_scans.totals([_summary_score(scan) for scan in result['scans']
                               if scan['file'] in FLOOR_SCANS])
    for gain in ('1', '4'):  # contrast against the road: the sensor's gain does not matter
        total = floor[gain]['all']
        assert total['labelled'] == 18, 'the floor is for the eight original sweeps'
        assert total['found'] >= FHLD_FOUND_FLOOR, out
        assert total['false'] <= FHLD_FALSE_CEILING * total['published'], out
    assert result['totals']['1'] == result['totals']['4'], out


def _summary_score(scan: dict) -> real_scans.ScanScore:
    """A ScanScore back from its JSON summary (for totals over a subset of the sweeps)."""
    return real_scans.ScanScore(scan['file'], scan['sensor'], scan['gain'], scan['line_cover'],
                                scan['lane_cover'])


def _striped_sweep(path, stripe_y: float = 2.0, half_width: float = 0.12) -> None:
    """A 16-laser spinning sweep (KITTI layout) of flat ground 1.7 m below the sensor, road
    intensity 0.1 and a painted stripe along x at stripe_y five times as bright."""
    elevation = np.radians(np.linspace(-25.0, -8.0, 16))[:, None]
    azimuth = np.radians(np.arange(0.0, 360.0, 0.25))[None]
    ground_range = 1.7 / np.tan(-elevation)
    x, y = ground_range * np.cos(azimuth), ground_range * np.sin(azimuth)
    intensity = np.where(np.abs(y - stripe_y) <= half_width, 0.5, 0.1)
    points = np.stack([x.ravel(), y.ravel(), np.full(x.size, -1.7), intensity.ravel()], axis=1)
    path.write_bytes(points.astype('<f4').tobytes())


def test_explain_measures_a_constructed_stripe(tmp_path, capsys: pytest.CaptureFixture) -> None:
    _striped_sweep(tmp_path / 'made.bin')
    line = [[x, 2.0, -1.7] for x in np.arange(-10.0, 10.5, 1.0)]
    labels = tmp_path / 'labels.json'
    labels.write_text(json.dumps({'scans': [{'file': 'made.bin', 'sensor': 'made', 'notes': 'x',
                                             'lines': [{'id': 'stripe', 'kind': 'solid',
                                                        'points': line}]}]}))
    figure = tmp_path / 'explain.png'
    out, result = _command([str(tmp_path), '--labels', str(labels), '--detector', 'classical',
                            '--explain', '--explain-figure', str(figure), '--json'], capsys)
    [facts] = result['lines']
    assert facts['line'] == 'stripe' and facts['verdict'] in real_scan_diagnosis.VERDICTS, out
    # the classical detector reads the absolute encoding: the table also gives `contrast`'s
    assert result['encoding'] == 'absolute' and facts['contrast_plain'] is not None, out
    assert facts['contrast'] > 2 and facts['contrast_plain'] > 2, out
    assert facts['rings'] >= 1 and facts['returns'] > 0, out
    assert facts['ring_spread'] == pytest.approx(0.0, abs=1e-6), 'all lasers read alike'
    assert figure.stat().st_size > 0 and 'stripe' in out


def test_diagnosis_helpers_on_constructed_points() -> None:
    # rings: elevation clusters; medians per ring; distances beside a polyline
    xyz = np.array([[10.0, 0, -1.0], [10.0, 0.1, -1.0], [5.0, 0, -1.0], [-5.0, 0, -1.0]])
    ids = elevation_ring_ids(xyz)  # the rings the diagnosis counts
    assert ids[0] == ids[1] and ids[2] == ids[3] and ids[0] != ids[2]
    medians = real_scan_diagnosis.group_medians(np.array([0, 0, 0, 1, 1, 2]),
                                                np.array([3.0, 1.0, 2.0, 4.0, 6.0, 9.0]), 2)
    assert medians.tolist() == [2.0, 5.0]
    polyline = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 1.0]])
    dist, z, beside = real_scan_diagnosis.line_frame(np.array([[5.0, 0.5], [12.0, 0.0]]),
                                                     polyline)
    assert np.allclose(dist, [0.5, 2.0]) and np.allclose(z, [0.5, 1.0])
    assert beside.tolist() == [True, False]
    assert [real_scan_diagnosis.verdict(*args, 0.7) for args in (
        (True, 0.9), (False, None), (False, 0.5), (False, 0.9))] == [
        'found', 'no-candidate', 'low-score', 'paint-check']
