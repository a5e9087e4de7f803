"""One parameter table: DetectorParams, its descriptions and config/lane_detector.yaml agree."""
import dataclasses
from pathlib import Path

import pytest

from fhld_ros.errors import CliError
from fhld_ros.ros.parameters import DESCRIPTIONS, DetectorParams, load_params_yaml

YAML = Path(__file__).resolve().parents[1] / 'config' / 'lane_detector.yaml'


def test_shipped_yaml_lists_every_parameter_at_its_default():
    assert load_params_yaml(YAML) == DetectorParams()
    text = YAML.read_text()
    for item in dataclasses.fields(DetectorParams):
        assert f'    {item.name}:' in text, item.name
        assert DESCRIPTIONS[item.name]
    assert set(DESCRIPTIONS) == {f.name for f in dataclasses.fields(DetectorParams)}


def test_bad_values_are_named(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('lane_detector:\n  ros__parameters:\n    refine_heights: 2\n'
                   '    detector: deep\n')
    with pytest.raises(CliError, match='detector must be .*refine_heights must be true or false'):
        load_params_yaml(bad)
    with pytest.raises(ValueError, match="detector must be 'fhld' or 'classical'"):
        DetectorParams(detector='deep')
    with pytest.raises(ValueError, match='local_refine_steps must be an integer >= 0'):
        DetectorParams(local_refine_steps=-1)
