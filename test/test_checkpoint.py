"""Checkpoint files: round trip with weights_only=True and one clear error per failure mode."""
from __future__ import annotations

import dataclasses
import os
import time

import pytest
import torch

import fhld_ros.model.checkpoint as checkpoint_module
from fhld_ros.errors import ConfigError
from fhld_ros.model.checkpoint import (
    FORMAT,
    CheckpointError,
    code_version,
    interpolate_checkpoints,
    load_checkpoint,
    save_checkpoint,
)
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.detector import FhldDetector


def small_config(**overrides) -> FhldConfig:
    base = dict(size_px=128, resolution_m=0.2, widths=(8, 16, 32, 64), d_model=64, ffn_dim=128,
                enc_layers=1, dec_layers=2, num_queries=6, cell_px=8, local_channels=16,
                local_hidden=64)
    return FhldConfig(**{**base, **overrides})


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(0)
    model = FhldDetector(small_config(cells_per_lane=20)).eval()
    path = save_checkpoint(tmp_path / 'ckpt' / 'model.pt', model,
                           train_command='fhld train --steps 10', meta={'val_f1': 0.5})
    return model, path


def test_round_trip_restores_model_config_and_provenance(saved):
    model, path = saved
    loaded = load_checkpoint(path)
    assert loaded.config == model.cfg and loaded.config.cells_per_lane == 20
    assert loaded.train_command == 'fhld train --steps 10'
    assert loaded.code_version == code_version() and loaded.meta == {'val_f1': 0.5}
    assert not loaded.model.training
    raster = torch.rand(1, 4, 128, 128)
    with torch.inference_mode():
        torch.testing.assert_close(loaded.model(raster)['curves'], model(raster)['curves'])
    raw = torch.load(path, weights_only=True)  # plain data only
    assert raw['format'] == FORMAT and isinstance(raw['config']['widths'], list)
    assert not list(path.parent.glob('.*.tmp'))  # the temp file was renamed


def test_half_precision_checkpoint_is_smaller_and_close(saved, tmp_path):
    model, path = saved
    half = save_checkpoint(tmp_path / 'half.pt', model, train_command='x', half=True)
    assert half.stat().st_size < 0.6 * path.stat().st_size
    raster = torch.rand(1, 4, 128, 128)
    with torch.inference_mode():
        torch.testing.assert_close(load_checkpoint(half).model(raster)['curves'],
                                   model(raster)['curves'], atol=0.02, rtol=0.02)


def test_default_model_checkpoint_fits_the_size_budget(tmp_path):
    path = save_checkpoint(tmp_path / 'default.pt', FhldDetector(FhldConfig()), 'x')
    assert path.stat().st_size <= 20 * 2 ** 20


def test_missing_file(tmp_path):
    with pytest.raises(CheckpointError, match='checkpoint not found: .*nope.pt'):
        load_checkpoint(tmp_path / 'nope.pt')


@pytest.mark.parametrize('damage', ['truncate', 'garbage', 'empty'])
def test_corrupt_file(saved, damage):
    _, path = saved
    data = path.read_bytes()
    path.write_bytes({'truncate': data[:len(data) // 2], 'garbage': b'\x00not a zip' * 50,
                      'empty': b''}[damage])
    with pytest.raises(CheckpointError, match='corrupt or not a torch file'):
        load_checkpoint(path)


def test_foreign_torch_file_is_rejected(tmp_path):
    path = tmp_path / 'other.pt'
    torch.save({'state_dict': {}}, path)
    with pytest.raises(CheckpointError, match='not an FHLD checkpoint'):
        load_checkpoint(path)


def test_pickled_objects_are_refused(tmp_path):
    path = tmp_path / 'pickled.pt'
    torch.save({'format': FORMAT, 'config': FhldConfig()}, path)  # a dataclass, not plain data
    with pytest.raises(CheckpointError, match='holds Python objects.*weights_only'):
        load_checkpoint(path)


def test_code_executing_pickle_is_named_and_never_run(tmp_path):
    # torch 2.13 words this refusal 'unsupported GLOBAL posix.mkdir whose module ...'
    canary = tmp_path / 'ran'

    class RunsCode:
        def __reduce__(self):
            return os.mkdir, (str(canary),)

    path = tmp_path / 'evil.pt'
    torch.save({'format': FORMAT, 'config': RunsCode()}, path)
    with pytest.raises(CheckpointError, match=r'holds Python objects \((posix|nt)\.mkdir\), not '
                                              'plain data: an unsafe pickle that could run code'):
        load_checkpoint(path)
    assert not canary.exists()


def edit_payload(path, **changes):
    payload = torch.load(path, weights_only=True)
    for key, value in changes.items():
        if key == 'config':
            payload['config'].update(value)
        else:
            payload[key] = value
    torch.save(payload, path)


def test_weights_that_do_not_fit_the_config(saved):
    _, path = saved
    edit_payload(path, config={'widths': [8, 16, 32, 32]})
    with pytest.raises(CheckpointError, match='does not fit the model built from its config'):
        load_checkpoint(path)


def test_missing_weights(saved):
    _, path = saved
    payload = torch.load(path, weights_only=True)
    del payload['state_dict']['global_branch.query_pos']
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match='does not fit.*query_pos'):
        load_checkpoint(path)


def test_unknown_config_field_and_newer_format(saved):
    _, path = saved
    edit_payload(path, config={'warp_drive': True})
    with pytest.raises(CheckpointError,
                       match=r'unusable config: unknown key\(s\) warp_drive in the model config'):
        load_checkpoint(path)
    edit_payload(path, format_version=99)
    with pytest.raises(CheckpointError, match='format version 99'):
        load_checkpoint(path)


def test_raster_spec_mismatch(saved):
    _, path = saved
    assert load_checkpoint(path, expect=FhldConfig(size_px=128, resolution_m=0.2)).model
    with pytest.raises(CheckpointError, match='expects a 128 px raster at 0.2 m.*640 px at 0.04'):
        load_checkpoint(path, expect=FhldConfig())


def test_checkpoint_from_before_a_config_field_existed(tmp_path):
    model = FhldDetector(small_config(stem_kernel=7))
    path = save_checkpoint(tmp_path / 'old.pt', model, 'x')
    payload = torch.load(path, weights_only=True)
    del payload['config']['stem_kernel']  # written before the field was added
    torch.save(payload, path)
    assert load_checkpoint(path).config.stem_kernel == 7


@pytest.mark.parametrize('change,message', [
    ({'d_model': 2 ** 20}, 'd_model must be an integer >= 1 and <= 4096, not 1048576'),
    ({'ffn_dim': 10 ** 7}, 'ffn_dim must be an integer >= 1'),
    ({'num_queries': 10 ** 6}, 'num_queries must be an integer >= 1 and <= 1000'),
    ({'enc_layers': 1000}, 'enc_layers must be an integer >= 0 and <= 64'),
    ({'size_px': 2 ** 16}, 'size_px must be an integer >= 32 and <= 4096'),
    ({'widths': [8, 16, 32, 2 ** 20]}, 'widths must be 4 integers >= 1 and <= 4096'),
    ({'roi_size': 10 ** 4}, 'roi_size must be an integer >= 1'),
    ({'cell_px': 256}, 'cell_px 256 exceeds size_px 128'),
    ({'d_model': '64'}, "d_model must be an integer >= 1 .*not '64'"),
    ({'d_model': 64.0}, 'd_model must be an integer >= 1 .*not 64.0'),
    ({'resolution_m': float('nan')}, 'resolution_m must be a number > 0, not nan'),
    ({'adaptive_axis': 1}, 'adaptive_axis must be true or false'),
])
def test_oversized_or_mistyped_configs_are_refused_before_a_model_is_built(
        saved, monkeypatch, change, message):
    # issue #17: d_model = 2**20 asked for 13 TB; the config is refused before any model exists
    _, path = saved
    edit_payload(path, config=change)

    def no_model(_config):
        raise AssertionError('a model was built from an unusable config')

    monkeypatch.setattr(checkpoint_module, 'FhldDetector', no_model)
    start = time.perf_counter()
    with pytest.raises(CheckpointError, match=f'unusable config: {message}'):
        load_checkpoint(path)
    assert time.perf_counter() - start < 5


def test_every_config_field_is_bounded():
    unbounded = [f.name for f in dataclasses.fields(FhldConfig) if f.type != 'bool'
                 and not {'range', 'choices'} & set(f.metadata)]
    assert unbounded == []


def test_checkpoints_from_before_the_contrast_encoding_read_absolute_intensity(tmp_path):
    path = save_checkpoint(tmp_path / 'old.pt', FhldDetector(small_config()), 'x')
    assert load_checkpoint(path).config.intensity_encoding == 'contrast'
    payload = torch.load(path, weights_only=True)
    del payload['config']['intensity_encoding']
    torch.save(payload, path)
    assert load_checkpoint(path).config.intensity_encoding == 'absolute'
    payload['config']['intensity_encoding'] = 'relative'
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="intensity_encoding must be 'absolute', 'contrast'"):
        load_checkpoint(path)


def test_interpolated_checkpoint_lies_between_its_sources(saved, tmp_path):
    start_model, start = saved
    torch.manual_seed(1)
    tuned_model = FhldDetector(start_model.cfg).eval()
    tuned = save_checkpoint(tmp_path / 'tuned.pt', tuned_model, 'fhld train --resume',
                            meta={'iteration': 7, 'train_state': {'optimizer': {}}})
    out = interpolate_checkpoints(start, tuned, 0.75, tmp_path / 'mix.pt')
    mixed = load_checkpoint(out)
    a, b = start_model.state_dict(), tuned_model.state_dict()
    for key, value in mixed.model.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value, 0.25 * a[key] + 0.75 * b[key])
    assert mixed.train_command == 'fhld train --resume'
    assert mixed.meta['iteration'] == 7 and 'train_state' not in mixed.meta
    assert mixed.meta['interpolated']['tuned_weight'] == 0.75
    with pytest.raises(ConfigError, match='within 0..1'):
        interpolate_checkpoints(start, tuned, 1.5, tmp_path / 'bad.pt')
    other = save_checkpoint(tmp_path / 'other.pt', FhldDetector(small_config()), 'x')
    with pytest.raises(CheckpointError, match='different model configs'):
        interpolate_checkpoints(start, other, 0.5, tmp_path / 'bad.pt')
    assert not (tmp_path / 'bad.pt').exists()
