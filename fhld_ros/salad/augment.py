"""SALAD's augmentation (paper §4.6), on virtual camera images with their 3D lanes.

* flip: the image mirrored left-right and every lane's x negated; exact because the virtual
  camera's principal point sits on the image's vertical centre line.
* joint 3D scale: the image zoomed by s about the principal point with the intrinsics kept,
  which is the camera moved along its axis: a point (x, y, z) is then seen where (x, y, z / s)
  was (paper eq. 9, with s the zoom). Zooming out leaves a black border, as a smaller sensor
  would.
* photometric: brightness, contrast and colour balance, which the 3D labels do not depend on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image

from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.virtual_camera import VirtualCamera


@dataclass(frozen=True)
class SaladAugment:
    flip: float = 0.5  # probability
    zoom: tuple[float, float] = (0.85, 1.25)  # s, log-uniform; (1, 1) turns it off
    brightness: float = 0.3  # x U(1 - b, 1 + b)
    contrast: float = 0.3
    colour: float = 0.08  # per channel x U(1 - c, 1 + c)


def flip(image: np.ndarray, lanes: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    return image[:, ::-1].copy(), [lane * np.array([-1.0, 1.0, 1.0]) for lane in lanes]


def zoom(image: np.ndarray, lanes: list[np.ndarray], camera: VirtualCamera,
         s: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """The image zoomed by s about the principal point (s > 1 enlarges), and its lanes."""
    if s == 1.0:
        return image, lanes
    # PIL maps output to input pixel-edge coordinates (a pixel centre u sits at u + 0.5)
    cu, cv = camera.cx + 0.5, camera.cy + 0.5
    data = (1 / s, 0.0, cu * (1 - 1 / s), 0.0, 1 / s, cv * (1 - 1 / s))
    out = Image.fromarray(image).transform((camera.width, camera.height), Image.AFFINE, data,
                                           resample=Image.BILINEAR)
    return np.asarray(out), [lane / np.array([1.0, 1.0, s]) for lane in lanes]


def photometric(image: np.ndarray, rng: np.random.Generator, aug: SaladAugment) -> np.ndarray:
    x = image.astype(np.float32)
    mean = x.mean()
    x = (x - mean) * rng.uniform(1 - aug.contrast, 1 + aug.contrast) + mean
    x *= rng.uniform(1 - aug.brightness, 1 + aug.brightness)
    x *= rng.uniform(1 - aug.colour, 1 + aug.colour, 3)
    return np.clip(x, 0, 255).astype(np.uint8)


def augment(sample: CameraLaneSample, camera: VirtualCamera, rng: np.random.Generator,
            aug: SaladAugment) -> tuple[np.ndarray, list[np.ndarray]]:
    """A virtual camera sample's image and lanes, randomly augmented."""
    image, lanes = sample.image, sample.lanes
    if rng.random() < aug.flip:
        image, lanes = flip(image, lanes)
    low, high = aug.zoom
    image, lanes = zoom(image, lanes, camera, float(np.exp(rng.uniform(np.log(low),
                                                                       np.log(high)))))
    return photometric(image, rng, aug), lanes
