"""The one camera SALAD sees: every image is resampled to a fixed virtual pinhole camera.

A network cannot read the focal length off an image, and depth scales with it: the same road
seen through a 50 or a 90 degree lens gives different depths at the same pixel. So images
from any camera are resampled, ray for ray, to VirtualCamera (same optical frame, square
pixels, fixed focal length and principal point); 3D lanes in the optical frame stay as they
are. Resampling is a scale and shift per axis (no skew): one antialiased PIL resize. A camera
with lens distortion (`camera/lens.py`: plumb_bob, rational_polynomial or equidistant, as
camera_info gives it) is undistorted on the way: the image
resized (antialiased) to the virtual focal length, then sampled bilinearly where the distortion
puts each virtual pixel's ray.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image

from fhld_ros.camera.calibration import corner_r2
from fhld_ros.camera.lens import Lens, as_lens
from fhld_ros.compiled import compiled
from fhld_ros.dataclass_dict import documented

# an image shrunk over 6x (a 4K camera's) is first box-averaged by whole factors, leaving 3-6x to
# the antialiased resize: 3840x2160 in 19 ms instead of 33, pixels a mean 0.4 levels apart
REDUCING_GAP = 3.0


@dataclass(frozen=True)
class VirtualCamera:
    """width x height pixels, focal length `focal` px, principal point at the horizontal centre
    (so a horizontal flip is exact) and `cy` px from the top (most rows below the horizon)."""

    # multiples of 32: the encoder halves the image five times. 640 px at focal 400 is a
    # 77-degree view: the 62 degrees of 480 px cut off lanes that the training cameras (50-90
    # degrees) see, and capped the decoding of perfect maps at F1 78.8 (77 degrees: 85.3;
    # docs/salad.md, "The width of the view"); the shipped weights' configs keep their 480
    width: int = documented(640, 'image width (px)', range='[64, 4096]')
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

    def warp(self, image: np.ndarray, k: np.ndarray, d: Lens | np.ndarray | None = None
             ) -> np.ndarray:
        """(H, W, 3) uint8 image of intrinsics k and lens distortion d (a Lens, or plumb_bob's
        k1 k2 p1 p2 [k3]; None or zeros: none) -> (height, width, 3) uint8 of this camera; what
        the source does not cover is black. ValueError for a skewed k."""
        k = np.asarray(k, dtype=np.float64)
        if abs(k[0, 1]) > 1e-6 * k[0, 0]:
            raise ValueError(f'intrinsics with skew {k[0, 1]:g} are not supported')
        lens = as_lens(d)
        if lens is not None:
            return self._undistort(image, k, lens)
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
            (c1 - c0, r1 - r0), Image.BILINEAR, box=box, reducing_gap=REDUCING_GAP)
        out[r0:r1, c0:c1] = np.asarray(patch)
        return out


    def _undistort(self, image: np.ndarray, k: np.ndarray, lens: Lens) -> np.ndarray:
        """warp() for a distorted camera: the part of the image the virtual camera sees, resized
        (antialiased) to the virtual focal length, then sampled bilinearly at each virtual
        pixel's distorted position."""
        h, w = image.shape[:2]
        remap = _undistort_map(self, tuple(k.ravel()), lens, (w, h))
        out = np.zeros((self.height * self.width, 3), dtype=np.uint8)
        if remap is not None:
            box, size, u, v = remap
            small = np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize(
                size, Image.BILINEAR, box=box, reducing_gap=REDUCING_GAP))
            sample_bilinear(small, u, v, out)
        return out.reshape(self.height, self.width, 3)


@lru_cache(maxsize=8)
def _undistort_map(camera: VirtualCamera, k: tuple[float, ...], lens: Lens,
                   source: tuple[int, int]
                   ) -> tuple[tuple[int, ...], tuple[int, int], np.ndarray, np.ndarray] | None:
    """(the source box the virtual camera sees, its size resized to the virtual focal length,
    and per virtual pixel (row-major) where its ray falls in that resized box: u, v pixel
    centres, NaN outside the image or where the polynomial folds back); None when nothing of
    the image is seen. Cached: a camera's map is the same for every image."""
    K = np.asarray(k).reshape(3, 3)
    w, h = source
    v, u = np.mgrid[0:camera.height, 0:camera.width].reshape(2, -1).astype(np.float64)
    x, y = (u - camera.cx) / camera.focal, (v - camera.cy) / camera.focal
    xd, yd = lens.distort(x, y)
    su, sv = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]  # source pixel centres
    seen = lens.unfolded(x, y, corner_r2(w, h, K)) & (su >= -0.5) & (su <= w - 0.5) & \
        (sv >= -0.5) & (sv <= h - 0.5)
    if not seen.any():
        return None
    # the source pixels around the seen positions, two more each side for the resize's filter
    left, top = (max(0, int(np.floor(c[seen].min())) - 2) for c in (su, sv))
    right = min(w, int(np.ceil(su[seen].max())) + 3)
    bottom = min(h, int(np.ceil(sv[seen].max())) + 3)
    size = (max(1, round((right - left) * camera.focal / K[0, 0])),
            max(1, round((bottom - top) * camera.focal / K[1, 1])))
    # PIL maps the box's edges onto the resized image's: centre c -> (c + 0.5 - edge) * scale
    u_small = (su + 0.5 - left) * size[0] / (right - left) - 0.5
    v_small = (sv + 0.5 - top) * size[1] / (bottom - top) - 0.5
    u_small[~seen] = np.nan
    return ((left, top, right, bottom), size, u_small.astype(np.float32),
            v_small.astype(np.float32))


@compiled
def sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """out[p] = image (H, W, C) uint8 sampled bilinearly at pixel centre (u[p], v[p]), clamped
    to the image; 0 where u[p] is NaN."""
    h, w, channels = image.shape
    for p in range(u.shape[0]):
        if u[p] != u[p]:
            for c in range(channels):
                out[p, c] = 0
            continue
        uc = min(max(np.float64(u[p]), 0.0), w - 1.0)
        vc = min(max(np.float64(v[p]), 0.0), h - 1.0)
        u0, v0 = int(uc), int(vc)
        u1, v1 = min(u0 + 1, w - 1), min(v0 + 1, h - 1)
        fu, fv = uc - u0, vc - v0
        for c in range(channels):
            upper = image[v0, u0, c] * (1.0 - fu) + image[v0, u1, c] * fu
            lower = image[v1, u0, c] * (1.0 - fu) + image[v1, u1, c] * fu
            out[p, c] = np.uint8(upper * (1.0 - fv) + lower * fv + 0.5)


def warm_sampler() -> None:
    """Compile sample_bilinear (or load it from numba's cache) with the types warp() calls it
    with."""
    nan = np.full(1, np.nan, dtype=np.float32)
    sample_bilinear(np.zeros((1, 1, 3), np.uint8), nan, nan, np.zeros((1, 3), np.uint8))


def _inside(coords: np.ndarray, size: int) -> tuple[int, int] | None:
    """[first, last + 1) of the ascending coords that lie within [-0.5, size - 0.5)."""
    inside = np.flatnonzero((coords >= -0.5) & (coords < size - 0.5))
    return (int(inside[0]), int(inside[-1]) + 1) if len(inside) else None
