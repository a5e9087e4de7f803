"""`fhld bench e2e --dds` and `camera_live --dds`: a node end to end over the DDS transports,
a process each."""
from __future__ import annotations

import math

import pytest

from fhld_ros.cli import build_parser

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LIGHT_PARAMS = 'detector:=classical size_px:=256 resolution_m:=0.1'


def test_bench_e2e_reports_both_transports(monkeypatch):
    from fhld_ros.commands import bench_e2e
    # the children read it from their environment, which bench_e2e builds from PARAMS
    monkeypatch.setenv('FHLD_BENCH_E2E_PARAMS', LIGHT_PARAMS)
    monkeypatch.setattr(bench_e2e, 'PARAMS', LIGHT_PARAMS.split())
    report = bench_e2e.bench_e2e(seconds=3, dds=('project', 'default'))
    for dds in ('project', 'default'):
        p50 = report[f'e2e_{dds}_latency_ms_p50']
        assert math.isfinite(p50) and p50 > 0, (dds, report)
        assert f'e2e_{dds}_node_clouds_lost_in_dds' in report
        assert not any(key.startswith(('e2e_e2e_', 'latency', 'sweeps')) for key in report)
    assert report['e2e_project_sweeps_published'] == 30


def test_bench_camera_live_names_its_transport():
    from fhld_ros.commands.bench_camera import bench_camera_live
    report = bench_camera_live(seconds=2, dds='default')
    assert report['camera_live_default_images_published'] == 20
    p50 = report['camera_live_default_latency_ms_p50']
    assert math.isfinite(p50) and p50 > 0, report
    assert 'camera_live_default_node_images_lost_in_dds' in report
    assert all(key.startswith('camera_live_default_') for key in report), report


def test_unknown_dds_transport_is_refused_by_argparse(capsys):
    with pytest.raises(SystemExit) as stop:
        build_parser('bench').parse_args(['bench', 'e2e', '--dds', 'nope'])
    assert stop.value.code == 2
    assert "invalid choice: 'nope'" in capsys.readouterr().err
