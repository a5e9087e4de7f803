"""A camera lane decoded between the two stripes of a double line is split into one lane per
stripe; a single line stays one lane (salad/double_lines.py)."""
import numpy as np
import pytest

from fhld_ros.salad.double_lines import split_double_lines
from fhld_ros.salad.virtual_camera import VirtualCamera

CAMERA = VirtualCamera()
HEIGHT_M = 1.5
ASPHALT, PAINT = 60, 200
STRIPE_M, GAP_M = 0.12, 0.14  # a double centre line: stripes 0.26 m apart, centre to centre
SINGLE_X = 3.5


def _road_image(double_x: float, dashed_left: bool) -> np.ndarray:
    """The virtual camera 1.5 m over a level road: a double line centred at double_x (its left
    stripe dashed, 3 m of every 12, with dashed_left), a single line at SINGLE_X."""
    v, u = np.mgrid[:CAMERA.height, :CAMERA.width].astype(float)
    below = v > CAMERA.cy + 1
    z = np.where(below, CAMERA.focal * HEIGHT_M / np.maximum(v - CAMERA.cy, 1e-3), np.inf)
    x = (u - CAMERA.cx) * z / CAMERA.focal
    half = 0.5 * (STRIPE_M + GAP_M)
    left = np.abs(x - (double_x - half)) < STRIPE_M / 2
    if dashed_left:
        left &= np.mod(np.where(below, z, 0.0), 12.0) < 3.0
    paint = below & (left | (np.abs(x - (double_x + half)) < STRIPE_M / 2)
                     | (np.abs(x - SINGLE_X) < STRIPE_M / 2))
    grey = np.where(below, np.where(paint, PAINT, ASPHALT), 170.0)
    return np.repeat(grey[..., None], 3, axis=2).astype(np.uint8)


def _lane(x: float) -> np.ndarray:
    z = np.arange(3.0, 50.0, 0.5)
    return np.stack([np.full_like(z, x), np.full_like(z, HEIGHT_M), z], axis=1)


@pytest.mark.parametrize('dashed_left', [False, True])
def test_a_lane_between_two_stripes_becomes_two_and_a_single_line_stays(dashed_left):
    image = _road_image(-1.75, dashed_left)
    lanes, scores = split_double_lines([_lane(-1.72), _lane(SINGLE_X + 0.03)],
                                       np.array([0.9, 0.8]), image, CAMERA)
    assert len(lanes) == 3
    np.testing.assert_allclose(scores, [0.9, 0.9, 0.8])
    half = 0.5 * (STRIPE_M + GAP_M)
    np.testing.assert_allclose([np.median(lane[:, 0]) for lane in lanes],
                               [-1.75 - half, -1.75 + half, SINGLE_X + 0.03], atol=0.03)
    np.testing.assert_allclose(lanes[0][:, 2], _lane(0.0)[:, 2])  # moved across only


def test_no_lanes_or_none_near_leave_nothing_to_split():
    image = _road_image(-1.75, False)
    lanes, scores = split_double_lines([], np.zeros(0), image, CAMERA)
    assert lanes == [] and scores.shape == (0,)
    far = _lane(-1.75)[80:]  # 43 m on: the stripes are not told apart there, nor tested
    lanes, scores = split_double_lines([far], np.array([0.7]), image, CAMERA)
    assert len(lanes) == 1 and lanes[0] is far


def test_the_node_takes_the_switch():
    from fhld_ros.salad.camera_pipeline import load_camera_detector
    from fhld_ros.salad.parameters import CameraParams
    assert CameraParams().double_lines
    assert not load_camera_detector(CameraParams(double_lines=False)).double_lines
