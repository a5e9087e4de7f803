"""The `fhld` command line: subcommands listed, errors as one clear line; an internal error
keeps its traceback."""
from __future__ import annotations

import json
import subprocess
import sys
import types

import pytest

from fhld_ros.cli import COMMANDS, main
from fhld_ros.errors import ConfigError


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


def _command(monkeypatch, error: Exception) -> None:
    """A subcommand 'boom' whose run raises error."""
    module = types.ModuleType('fhld_test_boom')
    module.add_arguments = lambda parser: None

    def run(args):
        raise error
    module.run = run
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(COMMANDS, 'boom', (module.__name__, 'raises'))


def test_a_config_error_is_one_line_and_exit_2(monkeypatch, capsys):
    _command(monkeypatch, ConfigError('rate_hz must be a number > 0, not -1'))
    assert main(['boom']) == 2
    assert capsys.readouterr().err == 'fhld boom: error: rate_hz must be a number > 0, not -1\n'


def test_an_internal_value_error_keeps_its_traceback(monkeypatch):
    _command(monkeypatch, ValueError('operands could not be broadcast together'))
    with pytest.raises(ValueError, match='broadcast'):
        main(['boom'])


def test_an_internal_value_error_in_training_is_not_a_config_error(monkeypatch, tmp_path):
    import fhld_ros.training.train as train_command

    def internal(*args, **kwargs):
        raise ValueError('operands could not be broadcast together')
    monkeypatch.setattr(train_command, 'train', internal)
    config = tmp_path / 'c.yaml'
    config.write_text('train: {iterations: 1}\n')
    with pytest.raises(ValueError, match='broadcast') as error:
        main(['train', '--config', str(config), '--out', str(tmp_path / 'run'), '--quiet'])
    assert not isinstance(error.value, ConfigError)
