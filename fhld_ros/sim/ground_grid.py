"""The ground heightfield cache the ray marcher reads (raycast.py): square tiles of height and
road coordinates (s, d) at GroundGrid.RES metres, built on demand from the analytic surface
(scene.py) and assembled into one block around the sensor. A LiDAR sees all around it; a
camera sees a sector, and builds only the tiles under it (tiles_in_sector): building a tile
is most of a camera render's time.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.sim.scene import Surface


class GroundGrid:
    """Heightfield cache: square tiles of h, s, d (float32) at RES metres, built on demand,
    and a block of tiles around the sensor assembled into one array for the ray marcher."""

    TILE_CELLS = 128
    RES = 0.5

    def __init__(self, surface: Surface, max_tiles: int = 96) -> None:
        self.surface = surface
        self.tile_m = self.TILE_CELLS * self.RES
        self._tiles: dict[tuple[int, int], np.ndarray] = {}
        self._max_tiles = max_tiles
        self._block_key: tuple[int, int, int, int] | None = None
        self.origin = np.zeros(2)
        self.h = self.s = self.d = np.zeros((0, 0), dtype=np.float32)
        self.padded_h = np.full((2, 2), -np.inf, dtype=np.float32)
        self.z_range = (0.0, 0.0)  # lowest and highest height of the block's built tiles
        self._skipped: set[tuple[int, int]] = set()  # the block's tiles left unbuilt

    def _tile(self, tx: int, ty: int) -> np.ndarray:
        tile = self._tiles.get((tx, ty))
        if tile is None:
            n, res = self.TILE_CELLS, self.RES
            c = (np.arange(n) + 0.5) * res
            x, y = np.meshgrid(tx * self.tile_m + c, ty * self.tile_m + c, indexing='xy')
            centre = (np.array([tx, ty]) + 0.5) * self.tile_m
            s, d = self.surface.ref.project(np.stack([x, y], axis=-1),
                                            (centre, np.sqrt(0.5) * self.tile_m))
            tile = np.stack([self.surface.height(s, d), s, d]).astype(np.float32)
            if len(self._tiles) >= self._max_tiles:  # drop the oldest tile
                self._tiles.pop(next(iter(self._tiles)))
            self._tiles[(tx, ty)] = tile
        return tile

    def ensure(self, xy: np.ndarray, radius: float,
               needed: set[tuple[int, int]] | None = None) -> None:
        """Make the block cover the square of half-size radius around xy. needed: build only
        these tiles of it (tiles_in_sector) and those cached, the others hold -inf heights that
        no ray finds: a camera sees a sector of the square, and building a tile is most of a
        render."""
        lo = np.floor((np.asarray(xy) - radius) / self.tile_m).astype(int)
        hi = np.floor((np.asarray(xy) + radius) / self.tile_m).astype(int)
        key = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
        if self._block_key is not None:
            k = self._block_key
            if k[0] <= key[0] and k[1] <= key[1] and k[2] >= key[2] and k[3] >= key[3] and \
                    (not self._skipped or (needed is not None and not needed & self._skipped)):
                return
        square = {(tx, ty) for tx in range(lo[0], hi[0] + 1) for ty in range(lo[1], hi[1] + 1)}
        skipped = set() if needed is None else square - needed - self._tiles.keys()
        unbuilt = np.zeros((3, self.TILE_CELLS, self.TILE_CELLS), dtype=np.float32)
        unbuilt[0] = -np.inf  # no ground; road coordinates 0 (concatenate copies it)
        rows = [np.concatenate([unbuilt if (tx, ty) in skipped else self._tile(tx, ty)
                                for tx in range(lo[0], hi[0] + 1)], axis=2)
                for ty in range(lo[1], hi[1] + 1)]
        block = np.concatenate(rows, axis=1)
        self.h, self.s, self.d = block[0], block[1], block[2]
        self.sd = np.ascontiguousarray(block[1:].reshape(2, -1).T.astype(np.float64))
        # one ring of -inf cells around: marching rays clipped onto it never find ground
        self.padded_h = np.pad(self.h, 1, constant_values=-np.inf)
        built = self.h[np.isfinite(self.h)]
        self.z_range = (float(built.min()), float(built.max())) if built.size else (0.0, 0.0)
        self.origin = lo * self.tile_m
        self._block_key = key
        self._skipped = skipped

    def tiles_near(self, xy: np.ndarray, margin: float) -> set[tuple[int, int]]:
        """The tiles within margin (< a tile) of any of the points xy (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        corners = np.concatenate([xy + (sx * margin, sy * margin)
                                  for sx in (-1, 1) for sy in (-1, 1)])
        ix, iy = np.floor(corners / self.tile_m).astype(np.int64).T
        lo_x, lo_y = int(ix.min()), int(iy.min())
        span = int(iy.max()) - lo_y + 1
        keys = np.unique((ix - lo_x) * span + (iy - lo_y))  # one integer per tile: a fast sort
        return {(lo_x + int(k) // span, lo_y + int(k) % span) for k in keys}

    def tiles_in_sector(self, xy: np.ndarray, azimuths: tuple[float, float], reach: float,
                        step: float = 4.0) -> set[tuple[int, int]]:
        """The tiles under the sector from xy out to reach between the azimuths (rad, low to
        high, world frame), with the cells beside it: sampled every `step` metres, each sample
        widened by a step and two cells."""
        radii = np.arange(0.0, reach + step, step)
        n_az = int(np.ceil((azimuths[1] - azimuths[0]) * reach / step)) + 1
        angles = np.linspace(azimuths[0], azimuths[1], n_az)
        points = np.asarray(xy)[:2] + radii[:, None, None] * np.stack(
            [np.cos(angles), np.sin(angles)], axis=-1)
        return self.tiles_near(points, step + 2 * self.RES)

    def nearest_h(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the cell containing each point (points outside: -inf, never ground)."""
        ny, nx = self.h.shape
        ix = np.floor((x - self.origin[0]) * (1.0 / self.RES)).astype(np.int32)
        iy = np.floor((y - self.origin[1]) * (1.0 / self.RES)).astype(np.int32)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = self.h.ravel()[np.where(ok, iy * nx + ix, 0)]
        return np.where(ok, out, -np.inf)

    def _corners(self, x: np.ndarray, y: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Flat index of the lower-left cell centre and the bilinear weights."""
        ny, nx = self.h.shape
        fx = np.clip((x - self.origin[0]) * (1.0 / self.RES) - 0.5, 0, nx - 1.0001)
        fy = np.clip((y - self.origin[1]) * (1.0 / self.RES) - 0.5, 0, ny - 1.0001)
        ix, iy = fx.astype(np.intp), fy.astype(np.intp)
        return iy * nx + ix, fx - ix, fy - iy, nx

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Cached height, bilinear between cell centres."""
        flat, wx, wy, nx = self._corners(x, y)
        h = self.h.ravel()
        top = h[flat] + (h[flat + 1] - h[flat]) * wx
        bottom = h[flat + nx] + (h[flat + nx + 1] - h[flat + nx]) * wx
        return top + (bottom - top) * wy

    def road_coords(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) by bilinear interpolation between cell centres (one gather per corner)."""
        flat, wx, wy, nx = self._corners(x, y)
        wx, wy = wx[:, None], wy[:, None]
        sd = self.sd
        top = sd[flat]
        top += (sd[flat + 1] - top) * wx
        bottom = sd[flat + nx]
        bottom += (sd[flat + nx + 1] - bottom) * wx
        top += (bottom - top) * wy
        return top[:, 0], top[:, 1]
