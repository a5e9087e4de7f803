"""Bird's-eye preview of a simulated run: accumulated ground intensity, GT lanes, ego path.

Points are accumulated in the odom frame with the reported /odom poses (what a consumer of
the bag would see), keeping returns near the road surface and within PREVIEW_RANGE_M of the
sensor; each pixel shows the brightest return.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

PREVIEW_RANGE_M = 40.0
MAX_PIXELS = 2400  # longest image side


class BevPreview:
    """Running max-intensity raster over the bounding box of the ego path."""

    def __init__(self, path_xy: np.ndarray, sensor_height: float = 1.95,
                 margin: float = 30.0) -> None:
        lo = path_xy.min(axis=0) - margin
        hi = path_xy.max(axis=0) + margin
        self.res = max(0.05, float((hi - lo).max()) / MAX_PIXELS)
        self.lo = lo
        self.shape = tuple(np.ceil((hi - lo) / self.res).astype(int)[::-1])  # rows (y), cols
        self.image = np.zeros(self.shape, dtype=np.float32)
        self.ground_below = 0.25 - sensor_height  # sensor-frame z of 'near the road surface'

    def add(self, xyz_sensor: np.ndarray, intensity01: np.ndarray, pose: np.ndarray) -> None:
        """One sweep: sensor-frame points (N, 3), intensity in [0, 1], sensor -> odom pose."""
        rng = np.linalg.norm(xyz_sensor[:, :2], axis=1)
        keep = (rng < PREVIEW_RANGE_M) & (xyz_sensor[:, 2] < self.ground_below) & np.isfinite(rng)
        world = xyz_sensor[keep].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        ij = np.floor((world[:, :2] - self.lo) / self.res).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < self.shape[1]) & (ij[:, 1] >= 0) & \
            (ij[:, 1] < self.shape[0])
        np.maximum.at(self.image, (ij[ok, 1], ij[ok, 0]), intensity01[keep][ok])

    def save(self, path: str | Path, lanes: list[np.ndarray], ego_xy: np.ndarray,
             title: str) -> None:
        h, w = self.shape
        scale = 12.0 / max(h, w)
        # no pyplot: no GUI backend, no global figure registry
        fig = Figure(figsize=(max(w * scale, 4.0), max(h * scale, 4.0) + 0.6),
                     dpi=max(100, int(max(h, w) / 12.0)))
        ax = fig.subplots()
        extent = (self.lo[0], self.lo[0] + w * self.res, self.lo[1], self.lo[1] + h * self.res)
        # gamma lifts the dim asphalt so the road texture is visible next to bright paint
        ax.imshow(np.sqrt(self.image), origin='lower', extent=extent, cmap='gray', vmin=0,
                  vmax=1, interpolation='nearest')
        for k, lane in enumerate(lanes):
            ax.plot(lane[:, 0], lane[:, 1], '-', lw=0.4, alpha=0.6,
                    color=('tab:cyan', 'tab:green', 'tab:orange', 'tab:pink')[k % 4])
        ax.plot(ego_xy[:, 0], ego_xy[:, 1], '-', color='red', lw=1.0, label='ego path')
        ax.plot(ego_xy[:1, 0], ego_xy[:1, 1], 'o', color='red', ms=4)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect('equal')
        ax.set_xlabel('x odom (m)')
        ax.set_ylabel('y odom (m)')
        ax.set_title(title, fontsize=9)
        ax.plot([], [], '-', color='tab:cyan', label='GT lane lines')
        ax.legend(loc='upper right', fontsize=7, framealpha=0.6)
        fig.tight_layout()
        fig.savefig(path)
