"""Camera lanes along paint are kept, along a kerb's edge dropped (salad/paint_evidence.py)."""
import numpy as np
import pytest

from fhld_ros.salad.paint_evidence import painted
from fhld_ros.salad.virtual_camera import VirtualCamera

CAMERA = VirtualCamera()
HEIGHT_M = 1.5
ASPHALT, PAINT, SIDEWALK = 60, 200, 150


def _road_image(paint_x: float, kerb_x: float, dashed: bool = False) -> np.ndarray:
    """The virtual camera 1.5 m over a level road, looking along it: asphalt, a line 0.15 m
    wide at paint_x (dashed: 3 m of every 12), a light sidewalk left of kerb_x."""
    v, u = np.mgrid[:CAMERA.height, :CAMERA.width].astype(float)
    below = v > CAMERA.cy + 1
    z = np.where(below, CAMERA.focal * HEIGHT_M / np.maximum(v - CAMERA.cy, 1e-3), np.inf)
    x = (u - CAMERA.cx) * z / CAMERA.focal
    grey = np.full(v.shape, 170.0)  # the sky
    grey[below] = ASPHALT
    line = below & (np.abs(x - paint_x) < 0.075)
    if dashed:
        line &= np.mod(np.where(below, z, 0.0), 12.0) < 3.0
    grey[line] = PAINT
    grey[below & (x < kerb_x)] = SIDEWALK
    return np.repeat(grey[..., None], 3, axis=2).astype(np.uint8)


def _lane(x: float, lateral_error: float = 0.0) -> np.ndarray:
    z = np.arange(3.0, 50.0, 0.5)
    return np.stack([np.full_like(z, x + lateral_error), np.full_like(z, HEIGHT_M), z], axis=1)


@pytest.mark.parametrize('dashed', [False, True])
def test_a_line_is_kept_and_a_lane_along_a_kerb_is_dropped(dashed):
    image = _road_image(1.8, -1.8, dashed)
    lanes = [_lane(1.8, 0.08), _lane(-1.8), _lane(-1.75, 0.1)]  # a few cm off, as decoded
    np.testing.assert_array_equal(painted(lanes, image, CAMERA, 1.3), [True, False, False])
    np.testing.assert_array_equal(painted(lanes, image, CAMERA, 0.0), [True] * 3)  # off
    # the road without paint: nothing stands out
    bare = _road_image(99.0, -1.8)
    assert not painted([_lane(1.8)], bare, CAMERA, 1.3).any()


def test_a_lane_with_the_road_beside_it_out_of_view_is_kept():
    image = _road_image(1.8, -1.8)
    far_side = _lane(60.0)  # right of the image from the first metre on: no evidence
    short = _lane(1.8)[:3]
    np.testing.assert_array_equal(painted([far_side, short], image, CAMERA, 1.3), [True, True])
    assert painted([], image, CAMERA, 1.3).shape == (0,)


def test_the_node_and_the_commands_take_the_contrast():
    from fhld_ros.errors import ConfigError
    from fhld_ros.salad.camera_pipeline import load_camera_detector
    from fhld_ros.salad.paint_evidence import MIN_CONTRAST
    from fhld_ros.salad.parameters import CameraParams
    assert CameraParams().min_paint_contrast == MIN_CONTRAST > 1.0
    assert load_camera_detector(CameraParams(min_paint_contrast=0.0)).min_paint_contrast == 0.0
    with pytest.raises(ConfigError, match='min_paint_contrast'):
        CameraParams(min_paint_contrast=-1.0)
