"""Bayer mosaics (a machine-vision camera's raw sensor image, sensor_msgs encodings
bayer_rggb8 / bggr8 / gbrg8 / grbg8) -> RGB, by bilinear interpolation: each pixel keeps its own
sample, and each missing colour is the mean of its nearest two or four samples of it. Every
mosaic is first made an RGGB one (a mirrored row or column above or left of it), so one set of
2x2-tile formulas, on quarter-resolution planes, serves all four."""
from __future__ import annotations

import numpy as np

# mirrored rows above, columns left that make the mosaic RGGB; red and blue then swapped
BAYER_PATTERNS = {'bayer_rggb8': (0, 0, False), 'bayer_bggr8': (0, 0, True),
                  'bayer_gbrg8': (1, 0, False), 'bayer_grbg8': (0, 1, False)}


def demosaic(raw: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W) uint8 mosaic -> (H, W, 3) uint8 RGB (image borders mirrored)."""
    top, left, swap = BAYER_PATTERNS[encoding]
    height, width = raw.shape
    bottom, right = (height + top) % 2, (width + left) % 2  # even sizes: whole tiles
    mosaic = np.pad(raw, ((top, bottom), (left, right)), mode='reflect')
    h2, w2 = mosaic.shape[0] // 2, mosaic.shape[1] // 2
    # mirrored by one more pixel all round (reflection keeps the pattern); plane(a, b)[i, j]
    # is the sample at padded (a + 2i, b + 2j), i.e. mosaic (2i + a - 1, 2j + b - 1)
    padded = np.pad(mosaic, 1, mode='reflect').astype(np.uint16)

    def plane(a: int, b: int) -> np.ndarray:
        return padded[a:a + 2 * h2:2, b:b + 2 * w2:2]

    def mean(*planes: np.ndarray) -> np.ndarray:
        return (sum(planes) + len(planes) // 2) // len(planes)

    red, blue = plane(1, 1), plane(2, 2)
    out = np.empty((h2, 2, w2, 2, 3), np.uint8)  # (tile row, row in tile, column, ...)
    tiles = {  # (row, column) in the tile: its red, green and blue
        (0, 0): (red, mean(plane(0, 1), plane(2, 1), plane(1, 0), plane(1, 2)),
                 mean(plane(0, 0), plane(0, 2), plane(2, 0), blue)),
        (0, 1): (mean(red, plane(1, 3)), plane(1, 2), mean(plane(0, 2), blue)),
        (1, 0): (mean(red, plane(3, 1)), plane(2, 1), mean(plane(2, 0), blue)),
        (1, 1): (mean(red, plane(1, 3), plane(3, 1), plane(3, 3)),
                 mean(plane(1, 2), plane(3, 2), plane(2, 1), plane(2, 3)), blue)}
    for (row, column), colours in tiles.items():
        for c, values in enumerate(colours):
            out[:, row, :, column, c] = values
    rgb = out.reshape(2 * h2, 2 * w2, 3)[top:top + height, left:left + width]
    return np.ascontiguousarray(rgb[..., ::-1] if swap else rgb)


def mosaic(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> the (H, W) mosaic a sensor with that pattern records of it."""
    top, left, swap = BAYER_PATTERNS[encoding]
    colour = np.array([[0, 1], [1, 2]])  # RGGB, then moved as the pattern is
    if swap:
        colour = 2 - colour
    colour = np.roll(colour, (-top, -left), axis=(0, 1))
    height, width = rgb.shape[:2]
    tiled = np.tile(colour, ((height + 1) // 2, (width + 1) // 2))[:height, :width]
    return np.take_along_axis(rgb, tiled[..., None], axis=2)[..., 0]
