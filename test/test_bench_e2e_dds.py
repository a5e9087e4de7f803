"""`fhld bench e2e --dds`: the node end to end over both DDS transports, a process each (the
same plumbing, bench_e2e.transport_child, runs `camera_live --dds`)."""
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


def test_unknown_dds_transport_is_refused_by_argparse(capsys):
    with pytest.raises(SystemExit) as stop:
        build_parser('bench').parse_args(['bench', 'e2e', '--dds', 'nope'])
    assert stop.value.code == 2
    assert "invalid choice: 'nope'" in capsys.readouterr().err
