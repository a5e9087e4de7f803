"""`fhld testset` end to end on a slice of the held-out set (the README table's command), and
its real-sensor conditions: what each one changes in the windows, and nothing else."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys

import numpy as np
import pytest

from fhld_ros.data.cache import TEST_SEED_BASE, scenario_for_seed
from fhld_ros.data.samples import _window_sweeps, scale_intensity, training_samples
from fhld_ros.evaluation import testset
from fhld_ros.evaluation.testset import CONDITIONS, WORN_PAINT_CONTRAST
from fhld_ros.intensity import ABSOLUTE, CONTRAST
from fhld_ros.parameters import DetectorParams
from fhld_ros.sim.lidar import ouster_dtype, velodyne_dtype
from fhld_ros.sim.simulator import Simulator


@pytest.mark.slow
def test_testset_scores_every_detector_overall_and_per_sensor():
    run = subprocess.run(
        [sys.executable, '-m', 'fhld_ros.cli', 'testset', '--seeds', '2',
         '--windows-per-seed', '1', '--workers', '1', '--detectors', 'classical', 'fhld',
         '--json'], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert (report['windows'], report['seeds']) == (2, 2)
    assert report['condition'] == 'none'
    sensors = sorted({scenario_for_seed(TEST_SEED_BASE + k)['sensor'] for k in range(2)})
    assert report['sensors'] == sensors and len(sensors) == 2
    assert set(report['detectors']) == {'classical', 'fhld'}
    # the shipped weights find lanes on these windows (the regression test has the thresholds)
    assert report['detectors']['fhld']['point']['F1@30'] > 50.0, report['detectors']
    assert report['detectors']['fhld']['lanes_per_window'] >= 1.0
    assert list(report['by_sensor']) == sensors
    for row in report['by_sensor'].values():
        assert row['windows'] == 1
        for name in ('classical', 'fhld'):
            assert 0.0 <= row[name]['F1@10'] <= row[name]['F1@30'] <= 100.0
    assert sum(row['windows'] for row in report['by_topology'].values()) == 2
    assert 'point F1@10 / F1@30 by sensor' in run.stdout
    assert report['paint_contrast'] > 5.0  # fresh paint


def test_intensity_gain_scales_floats_and_saturates_integer_fields():
    pts = np.zeros(4, dtype=velodyne_dtype('reflectivity'))  # uint16 reflectivity
    pts['reflectivity'] = [0, 100, 20000, 65535]
    pts['x'] = [1.0, 2.0, 3.0, 4.0]
    up = scale_intensity(pts, 4.0)
    assert up.dtype == pts.dtype and up['reflectivity'].tolist() == [0, 400, 65535, 65535]
    assert scale_intensity(pts, 0.25)['reflectivity'].tolist() == [0, 25, 5000, 16384]
    assert np.array_equal(up['x'], pts['x']) and pts['reflectivity'][1] == 100  # a copy
    floats = np.zeros(3, dtype=ouster_dtype('float'))
    floats['intensity'] = [0.1, 0.9, 1.0]
    assert np.allclose(scale_intensity(floats, 4.0)['intensity'], [0.4, 3.6, 4.0])  # unbounded
    assert scale_intensity(floats, 1.0) is floats
    no_field = np.zeros(2, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    assert scale_intensity(no_field, 2.0) is no_field


@pytest.mark.parametrize('name, field, kind, top', [
    ('units-float', 'intensity', np.float32, 1.0), ('units-u8', 'intensity', np.float32, 255.0),
    ('units-uint16', 'reflectivity', np.uint16, 255.0)])
def test_units_conditions_force_the_intensity_field(name, field, kind, top):
    for sensor in ('os1-32', 'vlp16'):  # an Ouster and a Velodyne layout
        sim = Simulator(2, sweeps=1, sensor=sensor, columns=256, **CONDITIONS[name].sim)
        p = sim.sweep(0).points
        assert p.dtype[field] == kind and p[field].max() <= top
        assert p[field].max() > (0.5 if top == 1.0 else 2.0)  # the whole scale, not 0-1


def test_gain_condition_changes_only_the_intensity_the_node_reads():
    sim = Simulator(2, sweeps=2, sensor='os1-32', columns=256, intensity='float')
    base, gained = (next(training_samples(sim, 1, sweeps_per_sample=2, keep_window=True,
                                          intensity_gain=g, intensity_encoding=ABSOLUTE))
                    for g in (1.0, 4.0))
    assert np.array_equal(base.window.points_window, gained.window.points_window)
    assert [a.tobytes() for a in base.lanes] == [a.tobytes() for a in gained.lanes]
    assert np.array_equal(base.raster[1:], gained.raster[1:])  # density and heights
    assert not np.array_equal(base.raster[0], gained.raster[0])  # intensity
    assert base.meta['paint_contrast'] == pytest.approx(gained.meta['paint_contrast'])
    contrast = [next(training_samples(sim, 1, sweeps_per_sample=2, intensity_gain=g,
                                      intensity_encoding=CONTRAST)).raster for g in (1.0, 4.0)]
    np.testing.assert_allclose(contrast[0], contrast[1], atol=1e-6)  # the gain cancels


def test_single_sweep_windows_hold_one_sweep_in_the_cloud_frame():
    assert list(_window_sweeps(40, 4, 10, 10, 0)) == [(k, k % 10 == 9) for k in range(40)]
    assert list(_window_sweeps(40, None, 1, 10, 9)) == [(k, True) for k in (9, 19, 29, 39)]
    assert [k for k, _ in _window_sweeps(30, 2, 10, 5, 0)] == list(range(15))  # overlapping
    sim = Simulator(3, sweeps=20, sensor='os1-64', columns=512, noise=False)
    samples = list(training_samples(sim, sweeps_per_sample=1, stride=10, start=9,
                                    odometry=False))
    assert [s.meta['sweep'] for s in samples] == [9, 19]
    assert all(s.meta['sweeps'] == 1 for s in samples)
    sample = samples[0]
    assert np.array_equal(sample.window_to_odom, np.eye(4))  # the cloud's own frame
    pose = sim.true_poses[9]  # GT in the sensor frame: lines on the road below the sensor
    world = [lane @ pose[:3, :3].T + pose[:3, 3] for lane in sample.lanes]
    assert sample.lanes and all(np.abs(lane[:, 2] + sim.mount.z).max() < 1.0
                                for lane in sample.lanes)
    gt = np.concatenate(sim.scene.lane_lines)
    for line in world:  # back in the world, each GT piece lies on a scene line
        dist = np.linalg.norm(line[:, None, :2] - gt[None, :, :2], axis=2).min(axis=1)
        assert dist.max() < 0.3
    with pytest.raises(ValueError, match='single sweeps'):
        next(training_samples(sim, 1, odometry=False))


def test_no_markings_and_single_sweep_through_evaluate_seed():
    """One seed's window through evaluate_seed (what each worker runs) for the conditions
    that change the windows' geometry or GT; the classical detector keeps it fast."""
    testset._init(['classical'], DetectorParams())
    seed = TEST_SEED_BASE + 4
    bare = testset.evaluate_seed(seed, 1, condition='no-markings')
    single = testset.evaluate_seed(seed, 1, condition='single-sweep')
    for result in (bare, single):
        assert result['windows'] == 1
        assert result['scenario'] == scenario_for_seed(seed)  # the seed's own sensor, topology
    assert bare['point']['classical'].n_gt == 0 and bare['once']['classical'].n_gt == 0
    assert single['once']['classical'].n_gt > 0
    report = testset.summarise([bare], ['classical'], 'no-markings')
    lanes = bare['once']['classical'].n_pred
    assert report['condition'] == 'no-markings' and report['paint_contrast'] is None
    row = report['detectors']['classical']
    assert row['lanes_per_window'] == row['false_lanes_per_window'] == lanes


def test_condition_table_and_bad_names():
    assert set(CONDITIONS) == {'gain-0.25', 'gain-0.5', 'gain-2', 'gain-4', 'units-float',
                               'units-u8', 'units-uint16', 'worn-paint', 'no-markings',
                               'single-sweep'}
    assert CONDITIONS['worn-paint'].sim == {'paint_contrast': WORN_PAINT_CONTRAST}
    parser = argparse.ArgumentParser()
    testset.add_arguments(parser)
    assert parser.parse_args(['--condition', 'gain-4']).condition == 'gain-4'
    assert parser.parse_args([]).condition is None
    with pytest.raises(SystemExit):
        parser.parse_args(['--condition', 'gain-3'])


@pytest.mark.slow
def test_testset_condition_end_to_end_reports_and_names_it():
    run = subprocess.run(
        [sys.executable, '-m', 'fhld_ros.cli', 'testset', '--seeds', '1',
         '--windows-per-seed', '1', '--workers', '1', '--detectors', 'classical',
         '--condition', 'worn-paint', '--json'], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report['condition'] == 'worn-paint' and report['windows'] == 1
    assert 1.0 < report['paint_contrast'] <= WORN_PAINT_CONTRAST
    assert 'condition: worn-paint' in run.stdout
    row = report['detectors']['classical']
    assert row['false_lanes_per_window'] <= row['lanes_per_window']
