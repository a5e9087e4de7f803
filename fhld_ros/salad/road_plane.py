"""RoadPlane: the road under a camera whose mount is known, as depth for the near lanes.

SALAD needs no extrinsics: its network gives every lane cell a depth. Where the mount is known
(a camera on a car: height over the road and pitch, e.g. the /tf_static transform from
base_footprint), the ray of a lane cell meets the road plane at a depth that is exact on a
level road, and the network's depth scatters by a few per cent from cell to cell, lane to lane
(docs/salad.md, "A known mount"). So up to `until_m` the plane gives the depth, from there to
1.5 x until_m it blends linearly into the network's, and beyond, where grades part the road
from the plane, the network's depth stands alone.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fhld_ros.salad.virtual_camera import VirtualCamera

UNTIL_M = 20.0  # chosen on SALAD's validation images (docs/salad.md, "A known mount")
BLEND = 1.5  # the plane's weight falls from 1 at until_m to 0 at BLEND x until_m
MIN_COSINE = 1e-6  # rays this close to parallel to the road never meet it


@dataclass(frozen=True)
class RoadPlane:
    """The road n . X = height_m in the camera's optical frame (x right, y down, z forward):
    n the unit normal pointing from the camera down to the road, height_m the camera's
    distance to it; the plane gives lane depths up to until_m. pitch_from_image: only the
    height and roll are to be trusted, the pitch is each image's own (lanes_road.image_road)."""

    normal: tuple[float, float, float]
    height_m: float
    until_m: float = UNTIL_M
    pitch_from_image: bool = False

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        if n.shape != (3,) or not np.isfinite(n).all() or abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise ValueError(f'the road normal must be a unit 3-vector, got {self.normal}')
        if not self.height_m > 0 or not self.until_m > 0:
            raise ValueError(f'the camera must be above the road (height {self.height_m:g} m) '
                             f'and until_m > 0 (got {self.until_m:g})')

    @classmethod
    def level(cls, height_m: float, pitch_rad: float, until_m: float = UNTIL_M) -> RoadPlane:
        """The road under a camera height_m above it, pitched down by pitch_rad, no roll."""
        return cls((0.0, float(np.cos(pitch_rad)), float(np.sin(pitch_rad))), height_m, until_m)

    @classmethod
    def from_extrinsic(cls, T_output_camera: np.ndarray, until_m: float = UNTIL_M,
                       pitch_from_image: bool = False) -> RoadPlane:
        """The output frame's z = 0 plane (its z axis up from the road, as base_footprint's)
        for a camera whose optical frame is T_output_camera (4 x 4) in it."""
        T = np.asarray(T_output_camera, dtype=np.float64)
        down = -T[2, :3]  # the output frame's -z, in optical coordinates
        return cls(tuple(float(c) for c in down / np.linalg.norm(down)), float(T[2, 3]),
                   until_m, pitch_from_image)

    @property
    def pitch_rad(self) -> float:
        """How far the camera looks down, over this road (radians)."""
        return float(np.arctan2(self.normal[2], self.normal[1]))

    def with_pitch(self, pitch_rad: float) -> RoadPlane:
        """This road seen from the camera pitched down by pitch_rad (its roll and height kept),
        as a fixed plane."""
        across = self.normal[0]
        along = np.sqrt(1.0 - across * across)
        return replace(self, normal=(across, float(along * np.cos(pitch_rad)),
                                     float(along * np.sin(pitch_rad))), pitch_from_image=False)

    def depth(self, u: np.ndarray, v: np.ndarray, camera: VirtualCamera) -> np.ndarray:
        """The depth (z) where the rays of pixels (u, v) meet the road; inf where they don't."""
        nx, ny, nz = self.normal
        cosine = (nx * (np.asarray(u) - camera.cx) + ny * (np.asarray(v) - camera.cy)
                  ) / camera.focal + nz
        return np.where(cosine > MIN_COSINE,
                        self.height_m / np.maximum(cosine, MIN_COSINE), np.inf)

    def blend(self, z: np.ndarray, u: np.ndarray, v: np.ndarray,
              camera: VirtualCamera) -> np.ndarray:
        """The network's depths z of pixels (u, v) with the plane's blended in (module doc)."""
        road = self.depth(u, v, camera)
        weight = np.clip((BLEND * self.until_m - road) / ((BLEND - 1.0) * self.until_m), 0, 1)
        return weight * np.where(weight > 0, road, 0.0) + (1.0 - weight) * z  # inf: weight 0
