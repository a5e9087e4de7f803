"""SALAD's augmentation (paper §4.6), on virtual camera images with their 3D lanes.

* flip: the image mirrored left-right and every lane's x negated; exact because the virtual
  camera's principal point sits on the image's vertical centre line.
* joint 3D scale: the image zoomed by s about the principal point with the intrinsics kept,
  which is the camera moved along its axis: a point (x, y, z) is then seen where (x, y, z / s)
  was (paper eq. 9, with s the zoom). Zooming out leaves a black border, as a smaller sensor
  would.
* photometric: brightness, contrast and colour balance, which the 3D labels do not depend on.

The draws, the flip and the lanes' scale are made per sample in the data loader (`draw`); the
zoom and the photometric change of the image are made on whole batches (`augment_images`), on
the training device: as numpy per sample they cost the loader more than the targets did, and on
a GPU the loader was what bounded the step rate.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from fhld_ros.salad.virtual_camera import VirtualCamera

# per image: zoom s, contrast, brightness, then the red, green and blue gains
IDENTITY = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], dtype=np.float32)


@dataclass(frozen=True)
class SaladAugment:
    flip: float = 0.5  # probability
    zoom: tuple[float, float] = (0.85, 1.25)  # s, log-uniform; (1, 1) turns it off
    brightness: float = 0.3  # x U(1 - b, 1 + b)
    contrast: float = 0.3
    colour: float = 0.08  # per channel x U(1 - c, 1 + c)


def flip(image: np.ndarray, lanes: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    return image[:, ::-1].copy(), [lane * np.array([-1.0, 1.0, 1.0]) for lane in lanes]


def draw(image: np.ndarray, lanes: list[np.ndarray], rng: np.random.Generator,
         aug: SaladAugment) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """(image, flipped or not; the lanes as the augmented image shows them; the image's
    parameters for augment_images)."""
    if rng.random() < aug.flip:
        image, lanes = flip(image, lanes)
    low, high = aug.zoom
    s = float(np.exp(rng.uniform(np.log(low), np.log(high))))
    params = np.array([s, rng.uniform(1 - aug.contrast, 1 + aug.contrast),
                       rng.uniform(1 - aug.brightness, 1 + aug.brightness),
                       *rng.uniform(1 - aug.colour, 1 + aug.colour, 3)], dtype=np.float32)
    return image, [lane / np.array([1.0, 1.0, s]) for lane in lanes], params


def augment_images(images: Tensor, params: Tensor, camera: VirtualCamera) -> Tensor:
    """(B, 3, H, W) images (any dtype, 0-255) and their (B, 6) draws -> (B, 3, H, W) float32:
    zoomed by s about the principal point (bilinear, black outside), then contrast about the
    image's mean, brightness and the channel gains, clipped to 0-255."""
    x = images.float()
    params = params.to(x)
    s = params[:, 0]
    # normalised coordinates (align_corners=False): pixel edges at -1 and 1; the principal
    # point's centre sits at (cx + 0.5) pixels from the left edge
    centre = torch.tensor([2 * (camera.cx + 0.5) / camera.width - 1,
                           2 * (camera.cy + 0.5) / camera.height - 1]).to(x)
    theta = torch.zeros(len(x), 2, 3).to(x)
    theta[:, 0, 0] = theta[:, 1, 1] = 1 / s
    theta[:, :, 2] = centre * (1 - 1 / s)[:, None]
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    x = F.grid_sample(x, grid, mode='bilinear', padding_mode='zeros', align_corners=False)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * params[:, 1, None, None, None] + mean
    x = x * (params[:, 2, None] * params[:, 3:6])[:, :, None, None]
    return x.clamp(0.0, 255.0)
