"""The rolling grid: sweeps kept in the output frame, and the window encoded around the newest.

RollingBevGrid keeps the last sweeps (by age and count), each as float32 offsets from its own
float64 pose, and encodes the window around the newest sweep with bev.RasterAccumulator; the
window's frame and channel conventions are those of bev.py.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from fhld_ros.bev import (
    HEIGHT_SHIFT_M,
    Z_REBASE_M,
    BevSpec,
    RasterAccumulator,
    pixel_coords,
    window_affine,
    yaw_frame,
)
from fhld_ros.intensity import ABSOLUTE, CONTRAST_RINGS, IntensityEncoder
from msg_adapters.pointcloud2 import DEFAULT_MAX_POINTS, read_xyzi, read_xyzir


@dataclass(frozen=True)
class _Sweep:
    """One sweep as stored: output-frame axes, float32 offsets from float64 references, so
    millimetres survive however far the vehicle is from the odometry origin."""

    stamp_ns: int
    pose: np.ndarray  # (4, 4) float64 sensor -> output
    xy: np.ndarray  # (2, N) float32 rows x - pose x, y - pose y
    e: np.ndarray  # (N,) float32 z - z_ref
    z_ref: float  # output-frame height that e is relative to (shared by the grid's sweeps)
    intensity01: np.ndarray  # (N,) float32 encoded intensity

    def with_z_ref(self, z_ref: float) -> _Sweep:
        e = self.e + np.float32(self.z_ref - z_ref)
        return _Sweep(self.stamp_ns, self.pose, self.xy, e, z_ref, self.intensity01)


@dataclass
class BevWindow:
    """One encoded window: the detector's input plus what is needed to publish in the output frame.

    points_window / intensity (the accumulated points inside the window, for the classical
    baseline) are computed on first access from the sweeps the raster was made of, so a window
    keeps those sweeps alive until then: to store many windows, store their rasters.
    """

    raster: np.ndarray  # (4, H, W) float32
    stamp_ns: int  # stamp of the newest sweep
    window_to_output: np.ndarray  # (4, 4) float64
    outline: np.ndarray  # (5, 3) closed polygon in the output frame, z at the window origin
    spec: BevSpec = field(default_factory=BevSpec)
    # (sweep, pixel affine) per sweep as rasterised, and the window height of e = 0
    _sources: tuple[tuple[_Sweep, np.ndarray], ...] = field(default=(), repr=False)
    _e_to_z: float = field(default=0.0, repr=False)

    @cached_property
    def _points(self) -> tuple[np.ndarray, np.ndarray]:
        size = self.spec.size_px
        xyz, inten = [np.zeros((0, 3), np.float32)], [np.zeros(0, np.float32)]
        for sweep, affine in self._sources:
            pix = pixel_coords(sweep.xy, affine)  # exactly as rasterised
            keep = ((pix >= 1) & (pix < size + 1)).all(axis=0)
            xy = self.spec.pixel_to_world(pix[:, keep].T - 1.0)
            xyz.append(np.column_stack([xy, sweep.e[keep] + self._e_to_z]).astype(np.float32))
            inten.append(sweep.intensity01[keep])
        self._sources = ()  # computed once: let the sweeps go
        return np.concatenate(xyz), np.concatenate(inten)

    @property
    def points_window(self) -> np.ndarray:
        """(N, 3) float32 accumulated points inside the window, window frame."""
        return self._points[0]

    @property
    def intensity(self) -> np.ndarray:
        """(N,) float32 normalised intensity of points_window."""
        return self._points[1]

    def to_output(self, points_window: np.ndarray) -> np.ndarray:
        """Window-frame points (..., 3) -> output frame (float64)."""
        T = self.window_to_output
        return np.asarray(points_window, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]

    def to_window(self, points_output: np.ndarray) -> np.ndarray:
        """Output-frame points (..., 3) -> window frame (float64)."""
        T = self.window_to_output
        return (np.asarray(points_output, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]


class RollingBevGrid:
    """Recent sweeps in the output frame, rasterised around the newest sensor pose on demand.

    Keeps the sweeps whose age w.r.t. the newest is < accumulate_sec, at most max_sweeps of
    them, so memory is bounded. A stamp older than the newest one (bag loop) resets the grid.
    """

    def __init__(self, spec: BevSpec = BevSpec(), accumulate_sec: float = 1.0,
                 max_sweeps: int = 10, intensity_encoding: str = ABSOLUTE) -> None:
        if not accumulate_sec >= 0 or max_sweeps < 1:
            raise ValueError('RollingBevGrid needs accumulate_sec >= 0 and max_sweeps >= 1')
        self.spec = spec
        self.encode_intensity = IntensityEncoder(intensity_encoding)
        self.accumulate_ns = round(accumulate_sec * 1e9)
        self.max_sweeps = int(max_sweeps)
        self._sweeps: deque[_Sweep] = deque()
        self._acc = RasterAccumulator(spec)

    def __len__(self) -> int:
        return len(self._sweeps)

    def reset(self) -> None:
        self._sweeps.clear()

    @property
    def newest_stamp_ns(self) -> int | None:
        return self._sweeps[-1].stamp_ns if self._sweeps else None

    def read_cloud(self, msg: Any, max_points: int | None = DEFAULT_MAX_POINTS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """A PointCloud2's xyz, raw intensity and, where this grid's encoding tells lasers
        apart (contrast_rings), its `ring` field (None when it has none): what insert takes.
        ValueError names what is malformed."""
        if self.encode_intensity.encoding == CONTRAST_RINGS:
            return read_xyzir(msg, max_points=max_points)
        return (*read_xyzi(msg, max_points=max_points), None)

    def insert(self, stamp_ns: int, xyz_sensor: np.ndarray, intensity_raw: np.ndarray,
               sensor_to_output: np.ndarray, intensity_scale: float | None = None,
               ring: np.ndarray | None = None) -> bool:
        """Add one sweep: sensor-frame points and the sensor pose at the sweep stamp.

        Use the identity pose without odometry. Points with a non-finite coordinate or
        intensity are dropped. intensity_scale fixes the absolute encoding's full scale (the
        contrast encoding needs none); ring, the points' ring field, tells contrast_rings
        the lasers apart. Returns True if the grid was reset (stamp older than newest).
        """
        stamp_ns = int(stamp_ns)
        pose = np.asarray(sensor_to_output, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ValueError('sensor_to_output must be a finite 4x4 matrix')
        xyz = np.asarray(xyz_sensor, dtype=np.float32).reshape(-1, 3)
        raw = np.asarray(intensity_raw).reshape(-1)
        if raw.shape[0] != xyz.shape[0]:
            raise ValueError(f'{xyz.shape[0]} points but {raw.shape[0]} intensities')
        reset = bool(self._sweeps) and stamp_ns < self._sweeps[-1].stamp_ns
        if reset:
            self.reset()
        x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        finite = np.isfinite(x + y + z + raw.astype(np.float32, copy=False))  # NaN/inf spread
        if not finite.all():
            xyz, raw = xyz[finite], raw[finite]
            x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            if ring is not None and np.shape(ring) == finite.shape:  # else left to the encoder
                ring = np.asarray(ring)[finite]
        intensity01 = self.encode_intensity(xyz, raw, intensity_scale, ring=ring)
        z_ref = self._z_ref_for(pose[2, 3])
        # rotate into output-frame axes (elementwise, as in pixel_coords)
        rot = pose[:3, :3].astype(np.float32)
        out = np.empty((3, x.shape[0]), dtype=np.float32)  # rows x, y, e
        for k in range(3):
            np.multiply(x, rot[k, 0], out=out[k])
            out[k] += y * rot[k, 1]
            out[k] += z * rot[k, 2]
        e = out[2]
        e += np.float32(pose[2, 3] - z_ref)
        self._sweeps.append(_Sweep(stamp_ns, pose, out[:2], e, z_ref,
                                   np.asarray(intensity01, dtype=np.float32)))
        self._evict()
        return reset

    def _z_ref_for(self, sensor_z: float) -> float:
        """Height reference for a new sweep: the nominal road below the sensor, shared by all
        held sweeps (re-based, rarely, when the road has moved more than Z_REBASE_M from it)."""
        road = sensor_z + HEIGHT_SHIFT_M
        if not self._sweeps:
            return road
        z_ref = self._sweeps[-1].z_ref
        if abs(road - z_ref) <= Z_REBASE_M:
            return z_ref
        self._sweeps = deque(sweep.with_z_ref(road) for sweep in self._sweeps)
        return road

    def _evict(self) -> None:
        newest = self._sweeps[-1].stamp_ns
        while len(self._sweeps) > self.max_sweeps or \
                newest - self._sweeps[0].stamp_ns >= max(self.accumulate_ns, 1):
            self._sweeps.popleft()

    def window(self, upto_ns: int | None = None) -> BevWindow | None:
        """Raster of the window centred on the newest sensor pose (None when no sweep is held);
        with upto_ns, of the sweeps stamped up to it, centred on the newest of those."""
        sweeps = [s for s in self._sweeps if s.stamp_ns <= upto_ns] if upto_ns is not None \
            else self._sweeps
        if not sweeps:
            return None
        spec, newest = self.spec, sweeps[-1]
        window_to_output = yaw_frame(newest.pose)
        rot, origin = window_to_output[:3, :3], window_to_output[:3, 3]  # window axes in output
        sources = []
        for sweep in sweeps:
            offset = (sweep.pose[:3, 3] - origin) @ rot  # the sweep's sensor origin, window frame
            sources.append((sweep, window_affine(rot[0, 0], rot[1, 0], offset, spec)))
        self._acc.clear()
        self._acc.add_all([(sweep.xy, affine, sweep.intensity01, sweep.e)
                           for sweep, affine in sources])
        e_to_z = newest.z_ref - origin[2]
        half = spec.length_m / 2
        corners = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0],
                            [-half, half, 0.0], [-half, -half, 0.0]])
        return BevWindow(self._acc.encode(e_to_z), newest.stamp_ns, window_to_output,
                         corners @ rot.T + origin, spec, tuple(sources), e_to_z)
