"""`fhld salad-average`: the mean of fine-tuned SALAD weights, refused across networks."""
from __future__ import annotations

import dataclasses

import torch

from fhld_ros.cli import main
from fhld_ros.salad.checkpoint import load_salad, save_salad


def _fine_tunes(tmp_path):
    """Two files of the shipped network: its weights, and each float tensor 1.0 more with
    another lane depth weight (as a fine-tune with --lane-depth-weight leaves them)."""
    model, _ = load_salad('salad')
    save_salad(tmp_path / 'a.pt', model, 'run a', {'steps': 10})
    shifted = {key: value + 1.0 if value.is_floating_point() else value
               for key, value in model.state_dict().items()}
    model.load_state_dict(shifted)
    model.cfg = dataclasses.replace(model.cfg, lane_depth_weight=1.25)
    save_salad(tmp_path / 'b.pt', model, 'run b', {'steps': 20})
    return load_salad(tmp_path / 'a.pt')[0].state_dict(), shifted


def test_the_mean_of_two_fine_tunes_keeps_the_last_config_and_both_provenances(tmp_path):
    first, second = _fine_tunes(tmp_path)
    out = tmp_path / 'soup' / 'salad.pt'
    assert main(['salad-average', str(out), str(tmp_path / 'a.pt'), str(tmp_path / 'b.pt')]) == 0
    model, info = load_salad(out)
    state = model.state_dict()
    for key, value in first.items():
        expected = 0.5 * (value + second[key]) if value.is_floating_point() else second[key]
        torch.testing.assert_close(state[key], expected)
    assert model.cfg.lane_depth_weight == 1.25
    assert [(run['train_command'], run['meta']['steps']) for run in info['meta']['averaged']] \
        == [('run a', 10), ('run b', 20)]


def test_other_networks_are_refused_and_nothing_is_overwritten(tmp_path, capsys):
    _fine_tunes(tmp_path)
    model, _ = load_salad('salad')
    model.cfg = dataclasses.replace(model.cfg, score_threshold=model.cfg.score_threshold + 0.1)
    save_salad(tmp_path / 'other.pt', model, 'other decoding')
    out = tmp_path / 'out.pt'
    assert main(['salad-average', str(out), str(tmp_path / 'a.pt'), str(tmp_path / 'other.pt')]) \
        == 2
    assert 'decode differently: score_threshold' in capsys.readouterr().err
    assert not out.exists()
    out.write_bytes(b'a user file')
    assert main(['salad-average', str(out), str(tmp_path / 'a.pt'), str(tmp_path / 'b.pt')]) == 2
    assert 'exists' in capsys.readouterr().err and out.read_bytes() == b'a user file'
    assert main(['salad-average', str(tmp_path / 'one.pt'), str(tmp_path / 'a.pt')]) == 2
    assert 'two or more' in capsys.readouterr().err
