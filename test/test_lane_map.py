"""The lane map's merge (annotation/lane_map.py): pieces of one line seen from many images
become one polyline; distinct lines, the stripes of a double line among them, and gaps where
nothing was seen stay apart."""
from __future__ import annotations

import numpy as np
import pytest

from fhld_ros.annotation.lane_map import build_lane_map
from fhld_ros.evaluation.metrics import point_to_polyline_2d


def piece(start: float, stop: float, offset: float = 0.0, noise: float = 0.0, seed: int = 0,
          radius: float | None = None) -> np.ndarray:
    """A lane every 0.5 m from station start to stop: straight along x at y = offset, or an
    arc of the given radius turning left; noise (m) moves each point across."""
    s = np.arange(start, stop + 1e-9, 0.5)
    across = offset + np.random.default_rng(seed).uniform(-noise, noise, len(s))
    if radius is None:
        return np.column_stack([s, across, np.full(len(s), -1.9)])
    angle = s / radius
    r = radius - across
    return np.column_stack([r * np.sin(angle), radius - r * np.cos(angle),
                            np.full(len(s), -1.9)])


def test_overlapping_pieces_of_one_line_become_one_line():
    # what consecutive images see of one line: 0-40 m ahead of a car moving 1.5 m per image
    pieces = [piece(1.5 * k, 1.5 * k + 40, noise=0.02, seed=k) for k in range(10)]
    lines = build_lane_map(pieces, [7] * 10)
    assert len(lines) == 1
    line = lines[0]
    assert line.label_id == 7
    assert line.points[0, 0] < 0.5 and line.points[-1, 0] > 53  # the union of the pieces
    assert np.abs(line.points[:, 1]).max() < 0.02  # the median across pieces
    assert np.allclose(line.points[:, 2], -1.9)


def test_a_curve_seen_both_ways_is_one_line():
    ahead = [piece(2.0 * k, 2.0 * k + 30, radius=60.0, noise=0.01, seed=k) for k in range(5)]
    lines = build_lane_map(ahead[:3] + [p[::-1] for p in ahead[3:]])
    assert len(lines) == 1
    truth = piece(0, 40, radius=60.0)
    assert point_to_polyline_2d(lines[0].points[:, :2], truth[:, :2]).max() < 0.02
    assert len(lines[0].points) >= 75  # 0-38 m every 0.5 m


def test_a_bad_piece_is_outvoted():
    pieces = [piece(k, k + 30, noise=0.01, seed=k) for k in range(6)]
    pieces.append(piece(2, 32, offset=0.08))  # one lift 8 cm off: still the same line
    lines = build_lane_map(pieces)
    assert len(lines) == 1 and np.abs(lines[0].points[:, 1]).max() < 0.02


def test_pieces_seen_near_outweigh_pieces_seen_far():
    # three images saw this stretch from 50 m away, 0.15 m off; two from 8 m, on the line
    far = [piece(0, 20, offset=0.15, seed=k) for k in range(3)]
    near = [piece(0, 20, seed=k) for k in range(2)]
    origins = [np.array([-50.0, 0.0])] * 3 + [np.array([-8.0, 0.0])] * 2
    weighted = build_lane_map(far + near, origins=origins)
    assert len(weighted) == 1 and np.abs(weighted[0].points[:, 1]).max() < 0.01
    plain = build_lane_map(far + near)  # the median alone follows the majority
    assert len(plain) == 1 and np.abs(plain[0].points[:, 1] - 0.15).max() < 0.01


@pytest.mark.parametrize('apart', [0.15, 0.2, 0.33])
def test_double_line_stripes_stay_two_lines(apart: float):
    # the simulator's double lines are 0.2-0.33 m apart centre to centre; each image shows both
    left = [piece(k, k + 30, offset=apart / 2, noise=0.02, seed=k) for k in range(6)]
    right = [piece(k, k + 30, offset=-apart / 2, noise=0.02, seed=10 + k) for k in range(6)]
    lines = build_lane_map(left + right, [1] * 6 + [2] * 6, images=[*range(6), *range(6)])
    assert sorted(line.label_id for line in lines) == [1, 2]
    for line in lines:
        expect = apart / 2 if line.label_id == 1 else -apart / 2
        assert np.abs(line.points[:, 1] - expect).max() < 0.03


def test_pieces_a_lift_put_decimetres_apart_are_still_one_line():
    # far lines shaded from the LiDAR, labels a few pixels off: pieces 0.2 m apart
    pieces = [piece(k, k + 30, offset=0.1 * (-1) ** k, seed=k) for k in range(7)]
    lines = build_lane_map(pieces)
    assert len(lines) == 1 and np.abs(np.median(lines[0].points[:, 1])) < 0.11


def test_lines_a_lane_apart_stay_apart():
    pieces = [piece(k, k + 30, offset=y) for k in range(3) for y in (-1.75, 1.75, 5.25)]
    assert len(build_lane_map(pieces, images=np.repeat(range(3), 3).tolist())) == 3


def test_a_gap_nothing_saw_stays_a_gap():
    near = [piece(k, k + 20) for k in range(3)]  # 0-22 m
    far = [piece(k, k + 15) for k in range(30, 33)]  # 30-47 m: hidden between
    lines = sorted(build_lane_map(near + far), key=lambda line: line.points[0, 0])
    assert len(lines) == 2
    assert lines[0].points[-1, 0] < 22.5 and lines[1].points[0, 0] > 29.5


def test_pieces_that_only_touch_are_joined():
    # they overlap by 1 m, too little to be grouped, and continue each other
    lines = build_lane_map([piece(0, 20)] * 3 + [piece(19, 40)] * 3)
    assert len(lines) == 1 and lines[0].points[-1, 0] > 39.5
    assert np.all(np.diff(lines[0].points[:, 0]) > 0)  # not back over the overlap


def test_what_too_few_images_saw_is_no_line():
    assert build_lane_map([]) == [] and build_lane_map([np.zeros((1, 3))]) == []
    assert build_lane_map([piece(0, 0.5)] * 3) == []  # shorter than a line
    # a lift gone wrong: no other image saw a line there
    lines = build_lane_map([piece(k, k + 20) for k in range(3)] + [piece(0, 20, offset=1.0)])
    assert len(lines) == 1 and np.abs(lines[0].points[:, 1]).max() < 0.01
