"""`fhld salad-train` as a run: a wall-clock budget (--minutes) that renders what fits and ends
its learning-rate schedule on time, fresh drives from --first-drive, and the clear errors."""
from __future__ import annotations

import re
import time

import numpy as np
import pytest
import torch

from fhld_ros.cli import main
from fhld_ros.salad import train
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, load_salad
from fhld_ros.salad.dataset import ShardSamples
from fhld_ros.salad.sim_source import camera_for_seed, salad_seeds
from fhld_ros.salad.virtual_camera import VirtualCamera

PEAK = 1e-3


def test_the_rate_warms_up_and_ends_at_zero_however_few_steps():
    assert train.learning_rate(0, 0.0, PEAK) == pytest.approx(PEAK / train.WARMUP_STEPS)
    assert train.learning_rate(train.WARMUP_STEPS, 0.0, PEAK) == pytest.approx(PEAK)
    assert train.learning_rate(train.WARMUP_STEPS, 0.5, PEAK) == pytest.approx(PEAK / 2)
    assert train.learning_rate(10, 1.0, PEAK) == 0.0  # a short run still ends at zero
    assert train.learning_rate(10_000, 2.0, PEAK) == 0.0


def test_a_timed_schedule_goes_by_the_clock_or_the_steps_whichever_is_further(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(train.time, 'monotonic', lambda: now[0])
    timed, by_steps, uncapped = (train.Schedule(1000, 60.0), train.Schedule(1000, None),
                                 train.Schedule(None, 60.0))
    now[0] += 30.0
    assert timed.progress(100) == pytest.approx(0.5) and by_steps.progress(100) == 0.1
    assert timed.progress(900) == pytest.approx(0.9)
    assert uncapped.progress(10**9) == pytest.approx(0.5)


def test_rendering_stops_at_its_time_and_leaves_no_partial_drive(tmp_path, capsys):
    seeds = salad_seeds('train', 2, start=11)
    train.build_cache(tmp_path, seeds, 1, VirtualCamera(), workers=2, seconds=0.0)
    assert list(tmp_path.iterdir()) == []  # cut off: no shard, no temporary file
    assert 'rendered 0 of 2 drives' in capsys.readouterr().err
    train.build_cache(tmp_path, seeds[:1], 1, VirtualCamera(), workers=1)
    assert [p.name for p in tmp_path.iterdir()] == [f'sim_{seeds[0]}.npz']


def test_a_timed_run_ends_within_its_minutes_with_its_schedule_done(tmp_path, capsys):
    out = tmp_path / 'run'
    start = time.monotonic()
    assert main(['salad-train', str(out), '--drives', '1', '--first-drive', '5', '--frames',
                 '1', '--batch', '1', '--workers', '0', '--threads', '1', '--lr', str(PEAK),
                 '--minutes', '0.3', '--render-share', '0.7',
                 '--init', str(DEFAULT_SALAD_CHECKPOINT)]) == 0
    assert time.monotonic() - start < 0.3 * 60 + 10  # the budget, and the save after it
    fifth = salad_seeds('train', 1, start=5)[0]
    assert [p.name for p in (out / 'cache').iterdir()] == [f'sim_{fifth}.npz']
    steps = [(int(m[1]), float(m[2])) for m in
             re.finditer(r'step (\d+) .* lr (\S+) time', capsys.readouterr().err)]
    assert steps and steps[-1][1] < 0.05 * PEAK  # the cosine ran out with the time
    _, info = load_salad(out / 'salad.pt')
    assert info['meta']['minutes'] == 0.3 and info['meta']['first_drive'] == 5
    assert info['meta']['steps'] == steps[-1][0] > 0
    # its clock is gone: not resumed
    assert main(['salad-train', str(out), '--drives', '0', '--resume', '--steps', '10']) == 2
    assert 'is a --minutes run' in capsys.readouterr().err


@pytest.mark.parametrize('flags, message', [
    (['--minutes', '1', '--resume'], 'not a --resume'),
    (['--minutes', '0'], 'must be > 0'),
    (['--minutes', '1', '--render-share', '1'], 'within'),
    (['--first-drive', str(10**6)], '--first-drive'),
])
def test_budget_and_drive_flags_are_checked(tmp_path, capsys, flags, message):
    assert main(['salad-train', str(tmp_path / 'run'), '--drives', '1', *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'run' / 'cache').exists()  # refused before any rendering


def test_drives_for_a_users_mount_are_rendered_and_named_apart(tmp_path):
    out = tmp_path / 'run'
    assert main(['salad-train', str(out), '--drives', '1', '--frames', '1', '--steps', '1',
                 '--batch', '1', '--workers', '0', '--threads', '1', '--camera-height', '2.6',
                 '--init', str(DEFAULT_SALAD_CHECKPOINT)]) == 0
    seed = salad_seeds('train', 1)[0]
    # the seeds' own cameras would be sim_<seed>.npz: a cache never mixes the two unasked
    assert [p.name for p in (out / 'cache').iterdir()] == [f'sim_{seed}_h2.60-2.60.npz']
    sample = ShardSamples([out / 'cache' / f'sim_{seed}_h2.60-2.60.npz']).lanes[0]
    pitch = np.radians(camera_for_seed(seed).pitch_deg)
    near = np.concatenate(sample)
    near = near[near[:, 2] < 15.0]
    below = near @ np.array([0.0, np.cos(pitch), np.sin(pitch)])  # the level road's normal
    assert abs(np.median(below) - 2.6) < 0.03 and np.abs(below - 2.6).max() < 0.15  # crowns
    assert load_salad(out / 'salad.pt')[1]['meta']['camera_heights_m'] == [2.6, 2.6]


def test_weights_train_on_a_wider_view_and_a_cache_keeps_its_width(tmp_path, capsys):
    out, narrow = tmp_path / 'run', tmp_path / 'narrow'
    tiny = ['--drives', '1', '--frames', '1', '--steps', '1', '--batch', '1', '--workers', '0',
            '--threads', '1']
    assert main(['salad-train', str(narrow), *tiny, '--camera-width', '480']) == 0
    narrow = narrow / 'salad.pt'
    run = ['salad-train', str(out), *tiny, '--init', str(narrow)]
    assert main([*run, '--camera-width', '640']) == 0
    before = load_salad(narrow)[0].cfg
    model = load_salad(out / 'salad.pt')[0]
    # wider, its rows (and their depth statistics) as the weights' it started from
    assert before.camera.width == 480 and model.cfg.camera.width == 640
    assert model.cfg.camera.height == before.camera.height and \
        model.cfg.row_shift == before.row_shift
    images = ShardSamples((out / 'cache').glob('*.npz')).images
    assert images and all(image.shape == (256, 640, 3) for image in images)
    # the same cache for those weights' own 480 px view: its images are not that camera's
    other = ['salad-train', str(tmp_path / 'other'), '--cache', str(out / 'cache'), *run[2:]]
    assert main(other) == 2
    assert 'holds 640x256 images, the virtual camera is 480x256: another --cache' in \
        capsys.readouterr().err
    assert main([*other, '--camera-width', '500']) == 2
    assert 'must be a multiple of 32 px each way' in capsys.readouterr().err
    # a resumed run keeps its view
    assert main(['salad-train', str(out), '--drives', '1', '--frames', '1', '--steps', '2',
                 '--resume', '--camera-width', '480']) == 2
    assert 'a resumed run keeps its camera (640 px wide)' in capsys.readouterr().err


def test_bfloat16_training_moves_float32_weights(tmp_path, monkeypatch, capsys):
    from fhld_ros.salad import train
    assert train.cpu_bf16_flags('flags\t\t: fpu avx2 avx512f avx512_bf16\nflags : amx_bf16') \
        == {'avx512_bf16', 'amx_bf16'}
    assert train.cpu_bf16_flags('flags\t\t: fpu sse avx2 fma\n') == set()
    out = tmp_path / 'run'
    monkeypatch.setattr(train, 'cpu_bf16_flags', lambda: set())  # an AVX2 CPU: refused
    assert main(['salad-train', str(out), '--drives', '1', '--frames', '1', '--steps', '2',
                 '--bf16']) == 2
    assert 'no bfloat16 instructions' in capsys.readouterr().err and not out.exists()
    monkeypatch.setattr(train, 'cpu_bf16_flags', lambda: {'avx512_bf16'})
    assert main(['salad-train', str(out), '--drives', '1', '--frames', '1', '--steps', '2',
                 '--batch', '1', '--workers', '0', '--threads', '1', '--bf16',
                 '--init', str(DEFAULT_SALAD_CHECKPOINT)]) == 0
    tuned, info = load_salad(out / 'salad.pt')
    shipped, _ = load_salad(DEFAULT_SALAD_CHECKPOINT)
    assert info['meta']['bf16'] is True and info['meta']['steps'] == 2
    weights = tuned.state_dict()
    assert all(w.dtype == torch.float32 for w in weights.values() if w.is_floating_point())
    assert all(torch.isfinite(w).all() for w in weights.values() if w.is_floating_point())
    assert any(not torch.equal(a, b) for a, b in zip(weights.values(),
                                                     shipped.state_dict().values()))
