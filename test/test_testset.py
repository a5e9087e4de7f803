"""`fhld testset` end to end on a slice of the held-out set (the README table's command)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fhld_ros.training.cache import TEST_SEED_BASE, scenario_for_seed


@pytest.mark.slow
def test_testset_scores_every_detector_overall_and_per_sensor():
    run = subprocess.run(
        [sys.executable, '-m', 'fhld_ros.cli', 'testset', '--seeds', '2',
         '--windows-per-seed', '1', '--workers', '1', '--detectors', 'classical', 'fhld',
         '--json'], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert (report['windows'], report['seeds']) == (2, 2)
    sensors = sorted({scenario_for_seed(TEST_SEED_BASE + k)['sensor'] for k in range(2)})
    assert report['sensors'] == sensors and len(sensors) == 2
    assert set(report['detectors']) == {'classical', 'fhld'}
    # the shipped weights find lanes on these windows (the regression test has the thresholds)
    assert report['detectors']['fhld']['point']['F1@30'] > 50.0, report['detectors']
    assert list(report['by_sensor']) == sensors
    for row in report['by_sensor'].values():
        assert row['windows'] == 1
        for name in ('classical', 'fhld'):
            assert 0.0 <= row[name]['F1@10'] <= row[name]['F1@30'] <= 100.0
    assert sum(row['windows'] for row in report['by_topology'].values()) == 2
    assert 'point F1@10 / F1@30 by sensor' in run.stdout
