"""One parameter table: DetectorParams, its field docs and config/lane_detector.yaml agree; every
config dataclass's values checked by one checker from what its fields declare.

That the node declares every field with its doc as the descriptor: test/test_node.py.
"""
import dataclasses
import math
from pathlib import Path

import pytest

from fhld_ros.data.cache import CacheSettings
from fhld_ros.dataclass_dict import field_docs
from fhld_ros.errors import ConfigError
from fhld_ros.model.config import FhldConfig
from fhld_ros.parameters import DetectorParams, load_params_yaml
from fhld_ros.training.augment import AugmentParams
from fhld_ros.training.config import DataSection, TrainSection

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
    with pytest.raises(ConfigError,
                       match='detector must be .*refine_heights must be true or false'):
        load_params_yaml(bad)
    with pytest.raises(ValueError, match="detector must be 'fhld' or 'classical'"):
        DetectorParams(detector='deep')
    with pytest.raises(ValueError, match='local_refine_steps must be an integer >= 0'):
        DetectorParams(local_refine_steps=-1)


def test_unknown_parameters_and_missing_sections_are_named(tmp_path):
    typo = tmp_path / 'typo.yaml'
    typo.write_text('lane_detector:\n  ros__parameters:\n    use_sim_time: true\n'
                    '    rate_hz: 5.0\n    rate: 5.0\n')
    with pytest.raises(ConfigError, match=r'typo\.yaml: unknown key\(s\) rate \('):
        load_params_yaml(typo)
    other = tmp_path / 'other.yaml'
    other.write_text('other_node:\n  ros__parameters:\n    rate_hz: 5.0\n')
    with pytest.raises(ConfigError, match='has no lane_detector: ros__parameters section'):
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


# Every config dataclass declares its values beside its docs and checks them with the one
# checker (dataclass_dict.check_fields): (how to build one with a field changed, its prefix)
def _detector(**change):
    return DetectorParams(**change)


def _checked(obj, where=''):
    def build(**change):
        changed = dataclasses.replace(obj, **change)
        changed.validate(*([where] if where else []))
        return changed
    return build


CHECKED = {
    'DetectorParams': (_detector, ''),
    'FhldConfig': (_checked(FhldConfig()), ''),
    'CacheSettings': (_checked(CacheSettings()), ''),
    'AugmentParams': (_checked(AugmentParams(), 'augment'), 'augment.'),
    'TrainSection': (_checked(TrainSection(), 'train'), 'train.'),
    'DataSection': (_checked(DataSection(), 'data'), 'data.'),
}
CLASSES = {'DetectorParams': DetectorParams, 'FhldConfig': FhldConfig,
           'CacheSettings': CacheSettings, 'AugmentParams': AugmentParams,
           'TrainSection': TrainSection, 'DataSection': DataSection}


def _bad(item: dataclasses.Field):
    """A value the field's declaration refuses (None when it declares no range or choices)."""
    meta, default = item.metadata, item.default
    if not {'range', 'choices'} & set(meta):
        return None
    items = isinstance(default, tuple)
    kind = meta.get('kind') or type(default[0] if items else default)
    if 'choices' in meta:
        bad = 3 if kind is int else 'nonsense'
    else:
        low, high, low_open, _ = meta['range']
        bad = (low if low_open else low - 1) if low > -math.inf else high + 1
        bad = int(bad) if kind is int else float(bad)
    return (bad, *default[1:]) if items else bad


@pytest.mark.parametrize('name', CLASSES)
def test_every_declared_range_and_choice_refuses_a_value_outside_it_naming_the_field(name):
    build, prefix = CHECKED[name]
    build()  # the defaults pass
    checked = [item for item in dataclasses.fields(CLASSES[name]) if _bad(item) is not None]
    assert checked
    for item in checked:
        bad = _bad(item)
        with pytest.raises(ConfigError) as error:
            build(**{item.name: bad})
        assert str(error.value).startswith(f'{prefix}{item.name} must be '), error.value
        assert f'not {bad!r}' in str(error.value), error.value


@pytest.mark.parametrize('build, message', [
    (lambda: FhldConfig(local_stride=12).validate('model'),
     'model.local_stride must be 4, 8, 16 or 32, not 12'),
    (lambda: FhldConfig(size_px=96, cell_px=128).validate(),
     'cell_px 128 exceeds size_px 96'),
    (lambda: CacheSettings(sensors=('vlp16', 'lidar9')).validate('data'),
     r"data.sensors must be one or more of 'vlp16', .* not \('vlp16', 'lidar9'\)"),
    (lambda: CacheSettings(windows_per_seed=0).validate(
        'data', {'windows_per_seed': 'train_windows_per_seed'}),
     'data.train_windows_per_seed must be an integer >= 1, not 0'),
    (lambda: AugmentParams(scale_min=1.2).validate('augment'),
     'augment.scale_min 1.2 exceeds augment.scale_max 1.1'),
    (lambda: TrainSection(schedule='linear').validate(),
     "train.schedule must be 'constant', 'cosine' or 'step', not 'linear'"),
    (lambda: TrainSection(step_milestones=(10, 'x')).validate(),
     r"train.step_milestones must be a list of integers >= 0, not \(10, 'x'\)"),
    (lambda: DataSection(train_seeds=(5, 5)).validate(),
     r'data.train_seeds must be \[start, stop\) with start < stop, not \[5, 5\]'),
    (lambda: DataSection(test_seeds=(100, 300)).validate(), 'overlap'),
    (lambda: DetectorParams(lidar_to_base=(0.0, 1.0)),
     r'lidar_to_base must be 6 finite numbers, not \(0.0, 1.0\)'),
    (lambda: DetectorParams(model_runtime='onnxruntime', device='cuda'),
     "model_runtime 'onnxruntime' needs device 'cpu'"),
])
def test_types_lengths_and_cross_field_rules_are_named(build, message):
    with pytest.raises(ConfigError, match=message):
        build()
