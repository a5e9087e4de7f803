"""Distillation (train.teacher): the student takes the teacher's layers, freezes all but its
global branch, learns the teacher's outputs, and runs and resumes as `fhld train`."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import MODEL, REPO, build_tiny_caches, load_payload, train_argv
from test_train import write_config as tiny_config

from fhld_ros.cli import main as fhld
from fhld_ros.model.checkpoint import load_checkpoint, save_checkpoint
from fhld_ros.model.detector import FhldDetector
from fhld_ros.training.config import cache_settings, load_config
from fhld_ros.training.distill import Teacher, fit_stem

pytestmark = pytest.mark.usefixtures('one_torch_thread')

TEACHER = dataclasses.replace(MODEL, enc_layers=2)  # the student (MODEL) has one layer


@pytest.fixture()
def teacher_path(tmp_path) -> Path:
    torch.manual_seed(0)
    return save_checkpoint(tmp_path / 'teacher.pt', FhldDetector(TEACHER).eval(), 'test')


def rasters(n: int = 2) -> torch.Tensor:
    return torch.rand(n, MODEL.in_channels, MODEL.size_px, MODEL.size_px,
                      generator=torch.Generator().manual_seed(1))


def test_the_student_takes_the_teachers_layers_and_trains_only_its_global_branch(teacher_path):
    teacher = load_checkpoint(teacher_path).model.state_dict()
    student = FhldDetector(MODEL)
    Teacher(str(teacher_path), student)
    for name, p in student.named_parameters():
        assert p.requires_grad == name.startswith('global_branch.'), name
    own = student.state_dict()
    assert all(torch.equal(value, teacher[key]) for key, value in own.items()), \
        'a layer the student shares with the teacher was not copied'
    skipped = sorted(set(teacher) - set(own))
    assert skipped and all('.encoder.1.' in key for key in skipped)


def test_the_loss_is_zero_for_the_teacher_itself_and_falls_as_the_student_learns(teacher_path):
    twin = FhldDetector(TEACHER)
    same = Teacher(str(teacher_path), twin).losses(twin, rasters())['loss']
    assert same < 1e-5  # float rounding

    student = FhldDetector(MODEL)
    teacher = Teacher(str(teacher_path), student)
    frozen = {k: v.clone() for k, v in student.state_dict().items()
              if not k.startswith('global_branch.')}
    opt = torch.optim.Adam([p for p in student.parameters() if p.requires_grad], lr=1e-3)
    first = teacher.losses(student, rasters())['loss'].item()
    for _ in range(40):
        loss = teacher.losses(student, rasters())['loss']
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert first > 0 and loss.item() < 0.5 * first
    after = student.state_dict()
    assert all(torch.equal(value, after[key]) for key, value in frozen.items()), \
        'a frozen layer (or a batch-norm statistic) changed'


def test_windows_without_lanes_teach_no_lane_and_the_others_the_teacher(teacher_path):
    twin = FhldDetector(TEACHER)
    teacher = Teacher(str(teacher_path), twin, no_lane_weight=2.0)
    lane = np.array([[0.0, -5.0, -1.8], [0.0, 5.0, -1.8]])
    assert teacher.losses(twin, rasters(), [[lane], [lane]])['loss'] < 1e-5
    with torch.no_grad():
        p_lane = twin.features(rasters())[0].softmax(-1)[:, 1:, :, 1]  # window 1: no lanes
    expected = 2.0 * -torch.log1p(-p_lane).sum() / p_lane.numel() / 2  # half the windows
    got = teacher.losses(twin, rasters(), [[lane], []])['loss_cls']
    assert torch.isclose(got, expected, rtol=1e-4), (got, expected)
    assert Teacher(str(teacher_path), twin).losses(twin, rasters(), [[lane], []])['loss'] < 1e-5


def test_a_student_that_changes_the_frozen_layers_is_refused(teacher_path):
    with pytest.raises(ValueError, match='differ from its teacher only in its global_branch'):
        Teacher(str(teacher_path), FhldDetector(dataclasses.replace(MODEL, local_hidden=16)))
    with pytest.raises(ValueError, match='reads intensity as'):
        Teacher(str(teacher_path),
                FhldDetector(dataclasses.replace(MODEL, intensity_encoding='absolute')))


def learn_for_30_steps(teacher: Teacher, student: FhldDetector,
                       frozen: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Train the student's trainable layers; the loss must halve and `frozen` stay as it is.
    Returns the first step's losses."""
    opt = torch.optim.Adam([p for p in student.parameters() if p.requires_grad], lr=1e-3)
    first = teacher.losses(student, rasters())
    for _ in range(30):
        loss = teacher.losses(student, rasters())['loss']
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first['loss'].item()
    after = student.state_dict()
    assert all(torch.equal(value, after[key]) for key, value in frozen.items())
    return first


def test_a_backbone_student_learns_the_teachers_features(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / 'stem5.pt',
                           FhldDetector(dataclasses.replace(MODEL, stem_kernel=5)).eval(), 'x')
    student = FhldDetector(MODEL)  # a 3 x 3 stem
    with pytest.raises(ValueError, match=r'\(train.distill\); it differs at backbone'):
        Teacher(str(path), FhldDetector(MODEL))
    teacher = Teacher(str(path), student, part='backbone')
    for name, p in student.named_parameters():
        assert p.requires_grad == name.startswith('backbone.'), name
    heads = {k: v.clone() for k, v in student.state_dict().items()
             if not k.startswith('backbone.')}
    first = learn_for_30_steps(teacher, student, heads)
    assert set(first) >= {'feature_4', 'feature_8', 'feature_16', 'feature_32'}
    with pytest.raises(ValueError, match='train.distill must be one of'):
        Teacher(str(path), FhldDetector(MODEL), part='heads')


def test_a_stem_student_trains_only_its_stem_and_the_two_stages_after_it(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / 'stem5.pt',
                           FhldDetector(dataclasses.replace(MODEL, stem_kernel=5)).eval(), 'x')
    student = FhldDetector(MODEL)  # a 3 x 3 stem
    teacher = Teacher(str(path), student, part='stem')
    trained = ('backbone.stem.', 'backbone.stages.0.', 'backbone.stages.1.')
    for name, p in student.named_parameters():
        assert p.requires_grad == name.startswith(trained), name
    frozen = {k: v.clone() for k, v in student.state_dict().items() if not k.startswith(trained)}
    assert any(k.startswith('backbone.stages.2.') for k in frozen)
    first = learn_for_30_steps(teacher, student, frozen)
    assert set(first) >= {'feature_4', 'feature_8', 'feature_16', 'feature_32'}
    wider = FhldDetector(dataclasses.replace(MODEL, widths=(8, 16, 32, 80)))
    with pytest.raises(ValueError, match=r'only in its backbone.stem, backbone.stages.0, '
                                         r'backbone.stages.1 \(train.distill\)'):
        Teacher(str(path), wider, part='stem')


def test_a_stem_student_with_an_output_weight_also_learns_what_the_branches_make_of_it(
        tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / 'stem5.pt',
                           FhldDetector(dataclasses.replace(MODEL, stem_kernel=5)).eval(), 'x')
    student = FhldDetector(MODEL)  # a 3 x 3 stem
    teacher = Teacher(str(path), student, part='stem', output_weight=2.0)
    trained = ('backbone.stem.', 'backbone.stages.0.', 'backbone.stages.1.')
    frozen = {k: v.clone() for k, v in student.state_dict().items() if not k.startswith(trained)}
    first = learn_for_30_steps(teacher, student, frozen)
    assert set(first) >= {'feature_4', 'feature_32', 'feature_local', 'loss_cls', 'loss_curve'}
    plain = Teacher(str(path), FhldDetector(MODEL), part='stem', copy_weights=False).losses(
        student, rasters())
    outputs = teacher.losses(student, rasters())
    extra = 2.0 * (outputs['loss_cls'] + outputs['loss_curve'] + outputs['feature_local'])
    assert outputs['loss'].item() == pytest.approx((plain['loss'] + extra).item(), rel=1e-5)
    assert extra.item() > 0
    twin = load_checkpoint(path).model
    assert Teacher(str(path), twin, part='stem', output_weight=2.0).losses(
        twin, rasters())['loss'] < 1e-5


def test_a_features_student_learns_all_the_teacher_computes_before_the_local_head(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / 'stem5.pt',
                           FhldDetector(dataclasses.replace(TEACHER, stem_kernel=5)).eval(), 'x')
    student = FhldDetector(MODEL)  # a 3 x 3 stem and one encoder layer fewer
    teacher = Teacher(str(path), student, part='features')
    trained = ('backbone.', 'local_features.', 'global_branch.')
    for name, p in student.named_parameters():
        assert p.requires_grad == name.startswith(trained), name
    head = {k: v.clone() for k, v in student.state_dict().items() if k.startswith('local_head.')}
    assert head
    first = learn_for_30_steps(teacher, student, head)
    assert set(first) >= {'feature_8', 'feature_16', 'feature_32', 'feature_local', 'loss_cls',
                          'loss_curve'}
    twin = load_checkpoint(path).model
    assert Teacher(str(path), twin, part='features').losses(twin, rasters())['loss'] < 1e-5
    with pytest.raises(ValueError, match=r'only in its backbone, local_features, global_branch'):
        Teacher(str(path), FhldDetector(dataclasses.replace(MODEL, local_hidden=16)),
                part='features')


def test_the_stem_fit_recovers_a_kernel_of_its_own_size_and_approximates_a_larger_one():
    raster = rasters(1)
    torch.manual_seed(2)
    same, larger = torch.nn.Conv2d(4, 8, 3, 2, 1, bias=False), torch.nn.Conv2d(4, 8, 7, 2, 3,
                                                                                bias=False)
    fitted = torch.nn.Conv2d(4, 8, 3, 2, 1, bias=False)
    fit_stem(fitted, same, raster)
    assert torch.allclose(fitted.weight, same.weight, atol=1e-4)
    fit_stem(fitted, larger, raster)
    error = (fitted(raster) - larger(raster)).pow(2).mean()
    centre = torch.nn.Conv2d(4, 8, 3, 2, 1, bias=False)
    with torch.no_grad():
        centre.weight.copy_(larger.weight[:, :, 2:5, 2:5])  # the naive stand-in
    assert error < (centre(raster) - larger(raster)).pow(2).mean()


@pytest.fixture(scope='module')
def caches(tmp_path_factory) -> Path:
    return build_tiny_caches(tmp_path_factory.mktemp('cache'))


@pytest.mark.slow
def test_fhld_train_distils_stops_and_resumes_exactly(caches, teacher_path, tmp_path):
    cfg = tiny_config(tmp_path / 'distil.yaml', caches, teacher=str(teacher_path))
    assert fhld(train_argv(cfg, tmp_path / 'a')) == 0
    straight = load_payload(tmp_path / 'a' / 'last.pt')
    assert straight['meta']['iteration'] == 3
    teacher = load_checkpoint(teacher_path).model.state_dict()
    for key, value in straight['state_dict'].items():
        if not key.startswith('global_branch.'):
            assert torch.equal(value, teacher[key]), key
    assert not torch.equal(straight['state_dict']['global_branch.query_pos'],
                           teacher['global_branch.query_pos'])
    log = [json.loads(line) for line in (tmp_path / 'a' / 'log.jsonl').read_text().splitlines()]
    assert all('loss_cls' in r and 'loss_curve' in r for r in log if 'loss' in r)
    assert straight['meta']['teacher']['path'] == str(teacher_path)

    run_b = train_argv(cfg, tmp_path / 'b')
    assert fhld([*run_b, '--max-minutes', '0']) == 0  # one iteration, then stop
    assert fhld([*run_b, '--resume']) == 0
    resumed = load_payload(tmp_path / 'b' / 'last.pt')
    for key, value in straight['state_dict'].items():
        assert torch.equal(value, resumed['state_dict'][key]), key


def test_init_and_teacher_together_are_one_clear_error(caches, teacher_path, tmp_path, capsys):
    cfg = tiny_config(tmp_path / 'both.yaml', caches, teacher=str(teacher_path),
                      init=str(teacher_path))
    assert fhld(train_argv(cfg, tmp_path / 'run')) == 2
    assert 'exclude each other' in capsys.readouterr().err


@pytest.mark.parametrize('name, value', [('distill_no_lane_weight', -1.0),
                                         ('distill_class_weight', float('nan')),
                                         ('distill_curve_weight', True),
                                         ('distill_output_weight', -0.5)])
def test_a_bad_distillation_weight_is_one_clear_error(caches, teacher_path, tmp_path, capsys,
                                                      name, value):
    cfg = tiny_config(tmp_path / 'bad.yaml', caches, teacher=str(teacher_path), **{name: value})
    assert fhld(train_argv(cfg, tmp_path / 'run')) == 2
    err = capsys.readouterr().err.strip()
    assert f'train.{name} must be a number >= 0' in err and len(err.splitlines()) == 1, err


@pytest.mark.parametrize('path', sorted((REPO / 'config').rglob('distill_*.yaml')),
                         ids=lambda p: p.name)
def test_distillation_configs_load_and_reuse_a_training_configs_cache(path):
    cfg = load_config(path)
    assert cfg.train.teacher and not cfg.train.init
    owners = [load_config(p) for p in (REPO / 'config').rglob('train_*.yaml')]
    owners = [o for o in owners if o.data.train_cache == cfg.data.train_cache]
    assert owners, f'no training config builds {cfg.data.train_cache}'
    assert all(cache_settings(o, 'train') == cache_settings(cfg, 'train') for o in owners)
