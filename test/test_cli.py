"""The `fhld` command line: subcommands listed, errors as one clear line."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fhld_ros.cli import COMMANDS, main


def _fhld(*args):
    return subprocess.run([sys.executable, '-m', 'fhld_ros.cli', *args], capture_output=True,
                          text=True, timeout=120)


def test_help_lists_every_subcommand():
    result = _fhld('--help')
    assert result.returncode == 0
    for name in COMMANDS:
        assert name in result.stdout


def test_help_imports_no_subcommand_module():
    code = ('import sys; from fhld_ros.cli import main\n'
            'try:\n    main(["--help"])\nexcept SystemExit:\n    pass\n'
            'print(sorted(m for m in ("torch", "rclpy", "fhld_ros.sim", "fhld_ros.training") '
            'if m in sys.modules))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == '[]'


def test_every_subcommand_builds_its_own_parser(capsys):
    for name in COMMANDS:
        with pytest.raises(SystemExit) as stop:
            main([name, '--help'])
        assert stop.value.code == 0, name
        assert capsys.readouterr().out.startswith(f'usage: fhld {name}'), name


def test_bench_adapters_reports_decode_speed_as_json():
    result = _fhld('bench', 'adapters', '--json')
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report['points_per_sweep'] == 64 * 1024
    assert report['decode_ms'] > 0
    assert report['decode_mpoints_per_s'] == report['points_per_sweep'] / report['decode_ms'] / 1e3


def test_unknown_bench_section_is_one_clear_error():
    result = _fhld('bench', 'nonsense')
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith('fhld bench: error: unknown section nonsense (choose from ')
