"""Writing commands never delete what they did not write (issue #17): `fhld replay`, `simulate`
and `demo` refuse an existing output unless --overwrite, which replaces only a rosbag2 bag
folder (or a regular file for file outputs), and refuse an output equal to, inside or containing
the input even with --overwrite. Every refusal is one error line, exit 2, and leaves the
directory tree byte for byte as it was."""
from __future__ import annotations

import argparse
import importlib
import os
import shutil
from pathlib import Path

import pytest

from fhld_ros.bagio import topic_counts
from fhld_ros.cli import COMMANDS, main

TINY = ['--sweeps', '3', '--sensor', 'os1-32', '--columns', '256', '--quiet']


def snapshot(root: Path) -> dict[str, object]:
    """Every entry under root: file bytes, link target or None for a folder."""
    def entry(p: Path) -> object:
        if p.is_symlink():
            return ('link', os.readlink(p))
        return p.read_bytes() if p.is_file() else None
    return {str(p.relative_to(root)): entry(p) for p in sorted(root.rglob('*'))}


def refused(capsys: pytest.CaptureFixture, root: Path, argv: list[str], text: str) -> None:
    """argv exits 2 with one error line holding text, and nothing under root changed."""
    capsys.readouterr()  # drop what earlier commands printed
    before = snapshot(root)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f'fhld {argv[0]}: error:' in err[0] and text in err[0], err
    assert snapshot(root) == before


@pytest.fixture(scope='module')
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp('drive') / 'drive'
    assert main(['simulate', str(path), '--seed', '3', *TINY]) == 0
    return path


@pytest.fixture
def tree(tmp_path: Path, drive: Path) -> Path:
    """tmp_path/data holding the input bag `in` next to a user's file and folder."""
    data = tmp_path / 'data'
    shutil.copytree(drive, data / 'in')
    (data / 'notes.txt').write_text('a regular file of the user')
    (data / 'results').mkdir()
    (data / 'results' / 'keep.csv').write_text('a folder with other files')
    return data


def replay(src: Path, out: Path, *extra: str) -> list[str]:
    return ['replay', str(src), str(out), '--detector', 'classical', '--quiet', *extra]


@pytest.mark.parametrize('overwrite', [[], ['--overwrite']])
def test_replay_keeps_what_it_did_not_write(tree: Path, capsys: pytest.CaptureFixture,
                                            overwrite: list[str]) -> None:
    src = tree / 'in'
    exists = 'exists and' if overwrite else 'exists (use --overwrite'
    cases = [
        (tree / 'results', exists),          # a folder with other files
        (tree / 'notes.txt', exists),        # a regular file
        (src, 'is IN_BAG'),                  # OUT = IN
        (src / 'lanes', 'is inside IN_BAG'),
        (tree, 'contains IN_BAG'),           # a parent of IN: IN and its siblings
        (tree.parent, 'contains IN_BAG'),
    ]
    for out, text in cases:
        refused(capsys, tree.parent, replay(src, out, *overwrite), text)
    (tree / 'alias').symlink_to(src)  # OUT is IN under another name
    refused(capsys, tree.parent, replay(src, tree / 'alias', *overwrite), 'is IN_BAG')


def test_replay_overwrite_replaces_only_a_bag(tree: Path, capsys: pytest.CaptureFixture) -> None:
    src, out = tree / 'in', tree / 'lanes'
    assert main(replay(src, out)) == 0
    first = snapshot(tree)
    refused(capsys, tree, replay(src, out), 'exists (use --overwrite to replace it)')
    assert main(replay(src, out, '--overwrite', '--params', str(params(tree, 5)))) == 0
    assert topic_counts(out)['/lanes'] < topic_counts(tree / 'in')['/points']
    assert snapshot(tree).keys() == first.keys() | {'rate.yaml'}  # no temporary left over
    assert snapshot(tree)['notes.txt'] == first['notes.txt']
    (out / 'labels.csv').write_text('the user put this in the bag folder')
    refused(capsys, tree, replay(src, out, '--overwrite'),
            'holds labels.csv, which the bag does not list: not replaced')
    refused(capsys, tree, replay(src, tree / 'results', '--overwrite'),
            'is not a rosbag2 bag (no metadata.yaml): not replaced')
    refused(capsys, tree, replay(src, tree / 'notes.txt', '--overwrite'),
            'is a file, not a rosbag2 bag folder')


def params(tree: Path, rate_hz: float) -> Path:
    """A parameter file slowing detection down, so a replaced bag differs from the first."""
    path = tree / 'rate.yaml'
    path.write_text(f'lane_detector:\n  ros__parameters:\n    rate_hz: {rate_hz}\n')
    return path


def simulate(out: Path, *extra: str) -> list[str]:
    return ['simulate', str(out), '--seed', '5', *TINY, *extra]


def test_simulate_keeps_what_it_did_not_write(tree: Path, capsys: pytest.CaptureFixture) -> None:
    for flags, text in (([], 'exists (use --overwrite'), (['--overwrite'], 'not replaced')):
        refused(capsys, tree, simulate(tree / 'results', *flags), text)
        refused(capsys, tree, simulate(tree / 'notes.txt', *flags), text)
    out, png = tree / 'sim', tree / 'sim.png'
    refused(capsys, tree, simulate(out, '--preview', str(out / 'p.png')), 'is inside OUT_BAG')
    assert main(simulate(out, '--preview', str(png))) == 0
    first = snapshot(tree)
    refused(capsys, tree, simulate(out), 'OUT_BAG')
    refused(capsys, tree, simulate(tree / 'other', '--preview', str(png)), '--preview')
    assert main(simulate(out, '--seed', '6', '--overwrite', '--preview', str(png))) == 0
    second = snapshot(tree)
    assert second.keys() == first.keys()
    assert second['sim.png'] != first['sim.png']
    assert second['sim/bag.mcap'] != first['sim/bag.mcap']
    assert second['in/bag.mcap'] == first['in/bag.mcap']
    (tree / 'link.png').symlink_to(tree / 'notes.txt')
    refused(capsys, tree, simulate(tree / 'x', '--overwrite', '--preview',
                                   str(tree / 'link.png')), 'symbolic link')
    (out / 'extra').mkdir()
    refused(capsys, tree, simulate(out, '--overwrite'), 'holds extra')


def test_every_writing_command_has_overwrite() -> None:
    for name in ('simulate', 'replay', 'import', 'demo'):
        parser = argparse.ArgumentParser()
        importlib.import_module(COMMANDS[name][0]).add_arguments(parser)
        assert '--overwrite' in parser.format_help(), name


@pytest.mark.slow
def test_demo_runs_again_only_with_overwrite(tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / 'demo'
    out.mkdir()
    (out / 'notes.txt').write_text('the user keeps notes here')
    demo = ['demo', '--out', str(out), '--sweeps', '4', '--detector', 'classical']
    assert main(demo) == 0
    capsys.readouterr()  # its progress output
    first = snapshot(out)
    assert {'sim', 'lanes', 'metrics.json', 'demo.png', 'notes.txt'} <= first.keys()
    refused(capsys, tmp_path, demo, 'exists (use --overwrite to replace it)')
    assert main([*demo, '--seed', '8', '--overwrite']) == 0  # what `make demo` runs again
    capsys.readouterr()
    second = snapshot(out)
    assert second.keys() == first.keys() and second['notes.txt'] == first['notes.txt']
    assert second['metrics.json'] != first['metrics.json']
    shutil.rmtree(out / 'lanes')
    (out / 'lanes').mkdir()
    (out / 'lanes' / 'mine.txt').write_text('not a bag')
    refused(capsys, tmp_path, [*demo, '--overwrite'], 'lanes exists and is not a rosbag2 bag')
    (out / 'lanes' / 'mine.txt').unlink()
    (out / 'lanes').rmdir()
    (out / 'demo.png').unlink()
    (out / 'demo.png').mkdir()
    refused(capsys, tmp_path, [*demo, '--overwrite'], 'demo.png exists and is not a regular file')
    refused(capsys, tmp_path, ['demo', '--out', str(out / 'notes.txt'), '--overwrite'],
            'is not a folder')
