"""`fhld eval` on small bags written with BagWriter: scores, JSON, CSV, plots, bad input."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from fhld_ros.bagio import BagWriter
from fhld_ros.cli import main
from fhld_ros.evaluation.metrics import clip_polyline_to_square
from fhld_ros.evaluation.window_region import (
    clip_polyline_to_polygon,
    window_frame,
    window_region,
)
from msg_adapters.lanes import lanes_to_marker_array

MARKERS = 'visualization_msgs/msg/MarkerArray'
HALF = 12.8
SEC = 1_000_000_000


def pose(x: float, y: float, yaw: float, z: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [x, y, z]
    return T


def outline(T: np.ndarray) -> np.ndarray:
    """bev.py's outline: rear-right, front-right, front-left, rear-left, rear-right."""
    c = np.array([[-HALF, -HALF, 0], [HALF, -HALF, 0], [HALF, HALF, 0], [-HALF, HALF, 0],
                  [-HALF, -HALF, 0]], dtype=float)
    return c @ T[:3, :3].T + T[:3, 3]


def road(lateral: float = 0.0) -> list[np.ndarray]:
    """Three 200 m GT lanes along the odom x axis (lanes leave every window)."""
    x = np.linspace(-100.0, 100.0, 201)
    return [np.column_stack([x, np.full_like(x, y + lateral), np.full_like(x, -1.3)])
            for y in (-3.5, 0.0, 3.5)]


POSES = [pose(10.0 * k, 0.5 * k, 0.3 * (k - 1)) for k in range(3)]  # yaw -0.3, 0, 0.3
STRAIGHT = [pose(10.0 * k, 0.5 * k, 0.0) for k in range(3)]


def pred_frames(shift: float = 0.0, drop: int | None = None,
                poses: list[np.ndarray] = POSES) -> list:
    """Whole GT road (eval clips it), shifted sideways, optionally without one lane."""
    lanes = road(shift)
    if drop is not None:
        lanes = lanes[:drop] + lanes[drop + 1:]
    return [((k + 1) * SEC // 10, lanes, outline(T)) for k, T in enumerate(poses)]


def write_gt(path: Path, lanes: list[np.ndarray], frame: str = 'odom',
             stamps: tuple[int, ...] = (0,)) -> Path:
    with BagWriter(path) as bag:
        fam = bag.family
        for stamp in stamps:
            msg = lanes_to_marker_array(fam, fam.header(stamp, frame), lanes,
                                        [1.0] * len(lanes), list(range(len(lanes))))
            bag.write('/lanes_gt', MARKERS, stamp, msg)
    return path


def write_pred(path: Path, frames: list[tuple[int, list[np.ndarray], np.ndarray | None]],
               frame: str = 'odom', topic: str = '/lanes') -> Path:
    with BagWriter(path) as bag:
        fam = bag.family
        for stamp, lanes, window in frames:
            msg = lanes_to_marker_array(fam, fam.header(stamp, frame), lanes,
                                        [0.9] * len(lanes), list(range(len(lanes))), window)
            bag.write(topic, MARKERS, stamp, msg)
    return path


@pytest.fixture
def gt_bag(tmp_path: Path) -> Path:
    return write_gt(tmp_path / 'gt', road())


def run_json(capsys: pytest.CaptureFixture, *argv: str) -> dict:
    assert main(['eval', *argv, '--json']) == 0
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


def run_error(capsys: pytest.CaptureFixture, *argv: str) -> str:
    assert main(['eval', *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('fhld eval: error: ') and '\n' not in err
    return err


def test_window_frame_matches_bev_outline() -> None:
    T = pose(5.0, -3.0, 0.7, z=1.2)
    origin, rot, half = window_frame(outline(T))
    np.testing.assert_allclose(origin, T[:3, 3])
    np.testing.assert_allclose(rot, T[:3, :3], atol=1e-12)
    assert half == pytest.approx(HALF)
    with pytest.raises(ValueError):
        window_frame(outline(T)[[0, 2, 1, 3, 4]])
    assert window_region(outline(T))[3] is None  # a square: clipped to as ever


def test_polygon_clip_of_a_square_is_the_square_clip() -> None:
    rng = np.random.default_rng(0)
    square = np.array([[-HALF, -HALF], [HALF, -HALF], [HALF, HALF], [-HALF, HALF]])
    for _ in range(50):
        lane = np.cumsum(rng.normal(0.0, 6.0, (12, 3)), axis=0) + rng.normal(0.0, 5.0, 3)
        want = clip_polyline_to_square(lane, HALF)
        got = clip_polyline_to_polygon(lane, square)
        assert len(got) == len(want)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, atol=1e-9)


def trapezoid(T: np.ndarray) -> np.ndarray:
    """A camera's footprint: 4 m wide 2 m ahead, 30 m wide 20 m ahead (near-right first,
    counter-clockwise, closed), posed by T."""
    c = np.array([[2, -2, 0], [20, -15, 0], [20, 15, 0], [2, 2, 0], [2, -2, 0]], dtype=float)
    return c @ T[:3, :3].T + T[:3, 3]


def test_polygon_window_clips_gt_to_the_region(tmp_path: Path, gt_bag: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    # lanes 3.5 m apart: left and right leave the trapezoid near the camera, the middle runs
    # through it; predicted: the GT where the camera sees it, and a lane outside it
    outside = np.column_stack([np.linspace(0, 12, 13), np.full(13, 14.0), np.full(13, -1.3)])
    frames = []
    for k, T in enumerate(POSES):
        region = trapezoid(T)
        seen = [part for lane in road() for part in clip_polyline_to_polygon(
            lane, region[:-1, :2])]
        frames.append(((k + 1) * SEC // 10, seen + [outside @ T[:3, :3].T + T[:3, 3]], region))
    origin, rot, half, polygon = window_region(frames[1][2])
    np.testing.assert_allclose(rot, POSES[1][:3, :3], atol=1e-12)  # x: into it, forward
    np.testing.assert_allclose(origin[:2], POSES[1][:2, 3] + [11.0, 0.0])
    assert half == pytest.approx(15.0) and polygon.shape == (4, 2)
    result = run_json(capsys, str(write_pred(tmp_path / 'pred', frames)), str(gt_bag),
                      '--plots', str(tmp_path / 'plots'), '--worst', '1')
    assert all(v == pytest.approx(100.0) for v in result['point'].values())
    assert result['once']['F1'] == pytest.approx(100.0)
    assert len(list((tmp_path / 'plots').glob('*.png'))) == 1  # the polygon drawn
    # the same lanes in the bounding square: the GT the camera does not see counts as missed
    squares = [(s, lanes, outline(T)) for (s, lanes, _), T in zip(frames, POSES)]
    result = run_json(capsys, str(write_pred(tmp_path / 'square', squares)), str(gt_bag))
    assert result['point']['R@30'] < 70


def test_identical_lanes_score_100_with_table_csv_and_plots(
        tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames())
    csv_path, plots = tmp_path / 'frames.csv', tmp_path / 'plots'
    result = run_json(capsys, str(pred), str(gt_bag), '--per-frame', str(csv_path),
                      '--plots', str(plots), '--worst', '2')
    assert set(result) >= {'frames', 'point', 'once'}
    assert result['frames'] == 3
    assert set(result['point']) == {'P@10', 'R@10', 'F1@10', 'P@30', 'R@30', 'F1@30'}
    assert set(result['once']) == {'P', 'R', 'F1', 'CD'}
    assert all(v == pytest.approx(100.0) for v in result['point'].values())
    assert result['once'] == pytest.approx({'P': 100.0, 'R': 100.0, 'F1': 100.0, 'CD': 0.0},
                                           abs=1e-6)
    rows = list(csv.DictReader(csv_path.open()))
    assert len(rows) == 3 and rows[0]['gt_lanes'] == '3' and float(rows[2]['F1@10']) == 100.0
    pngs = sorted(plots.glob('*.png'))
    assert len(pngs) == 2 and all(p.read_bytes()[:4] == b'\x89PNG' for p in pngs)


def test_table_without_json(tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames())
    assert main(['eval', str(pred), str(gt_bag)]) == 0
    out = capsys.readouterr().out
    assert 'within 10 cm' in out and 'ONCE-3DLanes (paper)' in out and '{' not in out


def test_shifts_in_the_window_frame(tmp_path: Path, gt_bag: Path,
                                    capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'p5', pred_frames(shift=0.05))
    point = run_json(capsys, str(pred), str(gt_bag))['point']
    assert point['P@10'] == point['R@10'] == 100.0
    pred = write_pred(tmp_path / 'p20', pred_frames(shift=0.2))
    result = run_json(capsys, str(pred), str(gt_bag))
    assert result['point']['P@10'] == result['point']['R@10'] == 0.0
    assert result['point']['P@30'] == result['point']['R@30'] == 100.0
    assert result['once']['CD'] == pytest.approx(0.2, abs=5e-3)
    official = run_json(capsys, str(pred), str(gt_bag), '--once-official')
    assert official['once_mode'] == 'official' and official['once']['P'] == 100.0


def test_missing_lane_lowers_recall_by_a_third(tmp_path: Path, gt_bag: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames(drop=0, poses=STRAIGHT))
    result = run_json(capsys, str(pred), str(gt_bag))
    assert result['point']['P@10'] == 100.0
    assert result['point']['R@10'] == pytest.approx(100 * 2 / 3)  # three equal chords
    assert result['once']['R'] == pytest.approx(100 * 2 / 3)


def test_gt_at_or_before_each_stamp(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # GT moves 20 cm sideways at t = 0.25 s: frames 1 and 2 see the old GT, frame 3 the new
    with BagWriter(tmp_path / 'gt') as bag:
        fam = bag.family
        for stamp, lanes in ((0, road()), (SEC // 4, road(0.2))):
            bag.write('/lanes_gt', MARKERS, stamp, lanes_to_marker_array(
                fam, fam.header(stamp, 'odom'), lanes, [1.0] * 3, [0, 1, 2]))
    pred = write_pred(tmp_path / 'pred', pred_frames())
    csv_path = tmp_path / 'f.csv'
    run_json(capsys, str(pred), str(tmp_path / 'gt'), '--per-frame', str(csv_path))
    f1 = [float(r['F1@10']) for r in csv.DictReader(csv_path.open())]
    assert f1 == [100.0, 100.0, 0.0]


# --- bad input ----------------------------------------------------------------------------

def test_unreadable_bag(tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    err = run_error(capsys, str(tmp_path / 'nope'), str(gt_bag))
    assert 'nope' in err and 'does not exist' in err
    junk = tmp_path / 'junk'
    junk.mkdir()
    (junk / 'metadata.yaml').write_text('not: a bag\n')
    assert 'junk' in run_error(capsys, str(junk), str(gt_bag))


def test_missing_topic(tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames(), topic='/other')
    err = run_error(capsys, str(pred), str(gt_bag))
    assert 'no topic /lanes' in err and '/other' in err
    pred = write_pred(tmp_path / 'pred2', pred_frames())
    err = run_error(capsys, str(pred), str(pred))
    assert 'no topic /lanes_gt' in err


def test_empty_bag_and_topic_without_messages(tmp_path: Path, gt_bag: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    with BagWriter(tmp_path / 'empty'):
        pass
    assert 'it has: nothing' in run_error(capsys, str(tmp_path / 'empty'), str(gt_bag))
    writer = Writer(tmp_path / 'silent', version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    writer.add_connection('/lanes', MARKERS, typestore=BagWriter(tmp_path / 'x').family.typestore)
    writer.close()
    assert 'no messages on /lanes' in run_error(capsys, str(tmp_path / 'silent'), str(gt_bag))


def test_wrong_message_type(tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    with BagWriter(tmp_path / 'pred') as bag:
        bag.write('/lanes', 'std_msgs/msg/String', 0, bag.family.new('std_msgs/msg/String'))
    assert 'not visualization_msgs/msg/MarkerArray' in run_error(
        capsys, str(tmp_path / 'pred'), str(gt_bag))


def test_frames_without_bev_window(tmp_path: Path, gt_bag: Path,
                                   capsys: pytest.CaptureFixture) -> None:
    frames = pred_frames()
    frames[1] = (frames[1][0], frames[1][1], None)
    err = run_error(capsys, str(write_pred(tmp_path / 'pred', frames)), str(gt_bag))
    assert '1 of 3 /lanes messages have no bev_window' in err and 'message 1' in err


def test_malformed_bev_window(tmp_path: Path, gt_bag: Path,
                              capsys: pytest.CaptureFixture) -> None:
    frames = pred_frames()
    square = frames[2][2]
    for k, order in enumerate(([0, 2, 1, 3, 4], [0, 1, 2, 3, 3], [0, 1, 0, 1, 0])):
        frames[2] = (frames[2][0], frames[2][1], square[order])  # crossing, open, no area
        err = run_error(capsys, str(write_pred(tmp_path / f'pred{k}', frames)), str(gt_bag))
        assert 'message 2' in err and 'not a closed square or simple polygon' in err, order


def test_frame_id_mismatch(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    gt = write_gt(tmp_path / 'gt', road(), frame='map')
    err = run_error(capsys, str(write_pred(tmp_path / 'pred', pred_frames())), str(gt))
    assert 'frame mismatch' in err and '"odom"' in err and '"map"' in err


def test_stamps_from_another_drive(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    gt = write_gt(tmp_path / 'gt', road(), stamps=(100 * SEC,))
    err = run_error(capsys, str(write_pred(tmp_path / 'pred', pred_frames())), str(gt))
    assert 'before the first /lanes_gt' in err and 'same drive' in err


# --- outputs: never delete what eval did not write (bagio's rule) -------------------------

def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob('*'))
            if p.is_file()}


def test_an_existing_per_frame_csv_is_replaced_only_with_overwrite(
        tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames())
    csv_path = tmp_path / 'frames.csv'
    csv_path.write_text('mine\n')
    err = run_error(capsys, str(pred), str(gt_bag), '--per-frame', str(csv_path))
    assert err == (f'fhld eval: error: --per-frame {csv_path} exists (use --overwrite to '
                   'replace it)')
    assert csv_path.read_text() == 'mine\n'
    run_json(capsys, str(pred), str(gt_bag), '--per-frame', str(csv_path), '--overwrite')
    assert csv_path.read_text().startswith('frame,stamp_ns,')
    link = tmp_path / 'link.csv'
    link.symlink_to(tmp_path / 'elsewhere.csv')
    err = run_error(capsys, str(pred), str(gt_bag), '--per-frame', str(link), '--overwrite')
    assert err.endswith('exists and is a symbolic link: not replaced')


def test_existing_plots_are_replaced_only_with_overwrite(
        tmp_path: Path, gt_bag: Path, capsys: pytest.CaptureFixture) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames())
    plots = tmp_path / 'plots'
    plots.mkdir()
    (plots / 'notes.txt').write_text('mine')
    (plots / 'frame_00001.png').write_bytes(b'mine')
    err = run_error(capsys, str(pred), str(gt_bag), '--plots', str(plots), '--worst', '2')
    assert err == (f'fhld eval: error: --plots {plots}/frame_00001.png exists (use --overwrite '
                   'to replace it)')
    assert _tree(plots) == {'notes.txt': b'mine', 'frame_00001.png': b'mine'}  # none written
    run_json(capsys, str(pred), str(gt_bag), '--plots', str(plots), '--worst', '2',
             '--overwrite')
    assert sorted(_tree(plots)) == ['frame_00000.png', 'frame_00001.png', 'notes.txt']
    assert (plots / 'frame_00001.png').read_bytes()[:4] == b'\x89PNG'
    assert (plots / 'notes.txt').read_text() == 'mine'  # what eval does not write is left alone
    (tmp_path / 'file').write_text('mine')
    err = run_error(capsys, str(pred), str(gt_bag), '--plots', str(tmp_path / 'file'))
    assert err == f'fhld eval: error: --plots {tmp_path}/file exists and is not a directory'


@pytest.mark.parametrize('where', ['PRED_BAG', 'GT_BAG'])
def test_outputs_equal_to_or_inside_an_input_bag_are_refused_even_with_overwrite(
        tmp_path: Path, capsys: pytest.CaptureFixture, where: str) -> None:
    pred = write_pred(tmp_path / 'pred', pred_frames())
    gt = write_gt(tmp_path / 'gt', road())
    bag = pred if where == 'PRED_BAG' else gt
    before = _tree(bag)
    storage = next(p for p in bag.iterdir() if p.suffix == '.mcap')
    for option, target, says in (
            ('--per-frame', bag, f'--per-frame {bag} is {where} {bag}'),
            ('--per-frame', storage, f'--per-frame {storage} is inside {where} {bag}'),
            ('--plots', bag, f'--plots {bag}/frame_00000.png is inside {where} {bag}'),
            ('--plots', bag / 'plots', f'--plots {bag}/plots is inside {where} {bag}')):
        err = run_error(capsys, str(pred), str(gt), option, str(target), '--overwrite')
        assert err == f'fhld eval: error: {says}: write it elsewhere', (option, target)
        assert _tree(bag) == before and not (bag / 'plots').exists()
    # an output that contains an input: tmp_path holds both bags
    err = run_error(capsys, str(pred), str(gt), '--per-frame', str(tmp_path), '--overwrite')
    assert err == f'fhld eval: error: --per-frame {tmp_path} contains PRED_BAG {pred}: write ' \
                  'it elsewhere'
