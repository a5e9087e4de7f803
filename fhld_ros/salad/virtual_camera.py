"""The one camera SALAD sees: every image is resampled to a fixed virtual pinhole camera.

A network cannot read the focal length off an image, and depth scales with it: the same road
seen through a 50 or a 90 degree lens gives different depths at the same pixel. So images
from any camera are resampled, ray for ray, to VirtualCamera (same optical frame, square
pixels, fixed focal length and principal point); 3D lanes in the optical frame stay as they
are. Resampling is a scale and shift per axis (no skew): one antialiased PIL resize.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image

from fhld_ros.dataclass_dict import documented


@dataclass(frozen=True)
class VirtualCamera:
    """width x height pixels, focal length `focal` px, principal point at the horizontal centre
    (so a horizontal flip is exact) and `cy` px from the top (most rows below the horizon)."""

    # multiples of 32: the encoder halves the image five times
    width: int = documented(480, 'image width (px)', range='[64, 4096]')
    height: int = documented(256, 'image height (px)', range='[64, 4096]')
    focal: float = documented(400.0, 'focal length (px)', range='(0, 100000]')
    cy: float = documented(89.5, 'principal point, px from the top', range='[0, 4096]')

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy],
                         [0.0, 0.0, 1.0]])

    def source_pixels(self, k: np.ndarray, u: np.ndarray, v: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Where virtual pixel coordinates (u, v) lie in an image of intrinsics k."""
        return (k[0, 2] + (u - self.cx) * k[0, 0] / self.focal,
                k[1, 2] + (v - self.cy) * k[1, 1] / self.focal)

    def warp(self, image: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 image of intrinsics k -> (height, width, 3) uint8 of this camera;
        what the source does not cover is black. ValueError for a skewed k."""
        k = np.asarray(k, dtype=np.float64)
        if abs(k[0, 1]) > 1e-6 * k[0, 0]:
            raise ValueError(f'intrinsics with skew {k[0, 1]:g} are not supported')
        h, w = image.shape[:2]
        # the virtual pixels whose centres fall inside the source image
        u_source, v_source = self.source_pixels(k, np.arange(self.width),
                                                np.arange(self.height))
        cols, rows = _inside(u_source, w), _inside(v_source, h)
        out = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        if cols is None or rows is None:
            return out
        (c0, c1), (r0, r1) = cols, rows
        # PIL boxes are in pixel-edge coordinates: a pixel centre u sits at u + 0.5
        u_edges, v_edges = self.source_pixels(k, np.array([c0 - 0.5, c1 - 0.5]),
                                              np.array([r0 - 0.5, r1 - 0.5]))
        box = (max(u_edges[0] + 0.5, 0.0), max(v_edges[0] + 0.5, 0.0),
               min(u_edges[1] + 0.5, float(w)), min(v_edges[1] + 0.5, float(h)))
        patch = Image.fromarray(np.ascontiguousarray(image)).resize(
            (c1 - c0, r1 - r0), Image.BILINEAR, box=box)
        out[r0:r1, c0:c1] = np.asarray(patch)
        return out


def _inside(coords: np.ndarray, size: int) -> tuple[int, int] | None:
    """[first, last + 1) of the ascending coords that lie within [-0.5, size - 0.5)."""
    inside = np.flatnonzero((coords >= -0.5) & (coords < size - 0.5))
    return (int(inside[0]), int(inside[-1]) + 1) if len(inside) else None
