"""One parameter table: DetectorParams, its field docs and config/lane_detector.yaml agree.

That the node declares every field with its doc as the descriptor: test/test_node.py.
"""
import dataclasses
from pathlib import Path

import pytest

from fhld_ros.dataclass_dict import field_docs
from fhld_ros.errors import CliError
from fhld_ros.parameters import DetectorParams, load_params_yaml

YAML = Path(__file__).resolve().parents[1] / 'config' / 'lane_detector.yaml'


def test_shipped_yaml_lists_every_parameter_at_its_default():
    assert load_params_yaml(YAML) == DetectorParams()
    text = YAML.read_text()
    for item in dataclasses.fields(DetectorParams):
        assert f'    {item.name}:' in text, item.name


def test_every_parameter_has_a_description():
    docs = field_docs(DetectorParams)
    assert set(docs) == {f.name for f in dataclasses.fields(DetectorParams)}
    assert [name for name, doc in docs.items() if len(doc) < 10] == []


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


def test_unknown_parameters_and_missing_sections_are_named(tmp_path):
    typo = tmp_path / 'typo.yaml'
    typo.write_text('lane_detector:\n  ros__parameters:\n    use_sim_time: true\n'
                    '    rate_hz: 5.0\n    rate: 5.0\n')
    with pytest.raises(CliError, match=r'typo\.yaml: unknown key\(s\) rate \('):
        load_params_yaml(typo)
    other = tmp_path / 'other.yaml'
    other.write_text('other_node:\n  ros__parameters:\n    rate_hz: 5.0\n')
    with pytest.raises(CliError, match='has no lane_detector: ros__parameters section'):
        load_params_yaml(other)


def test_wildcard_section_and_lists_as_tuples(tmp_path):
    wildcard = tmp_path / 'wildcard.yaml'
    wildcard.write_text('/**:\n  ros__parameters:\n    use_sim_time: true\n    rate_hz: 5.0\n'
                        '    lidar_to_base: [1.0, 0.0, 2.0, 0.0, 0.0, 0.0]\n')
    assert load_params_yaml(wildcard) == DetectorParams(
        rate_hz=5.0, lidar_to_base=(1.0, 0.0, 2.0, 0.0, 0.0, 0.0))


@pytest.mark.parametrize('value', [0, -1, True, 1.5, '1000'])
def test_max_points_must_be_a_positive_integer(value):
    with pytest.raises(ValueError, match='max_points must be an integer > 0'):
        DetectorParams(max_points=value)


def test_max_points_default_holds_a_128_by_2048_sensor_with_margin():
    assert DetectorParams().max_points == 2 ** 20 >= 4 * 128 * 2048
    assert DetectorParams(max_points=128 * 2048).max_points == 262144
