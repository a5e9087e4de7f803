"""Bird's-eye-view encoding: sweeps -> rolling point buffer -> 4-channel raster (FHLD input).

One code path for training samples, bag replay and the live node, so there is no
training/serving skew. Conventions (fixed, ARCHITECTURE.md):

* Window frame: origin at the newest sweep's sensor position, x forward along its heading
  (yaw only, gravity aligned), y left, z up; heights are relative to the sensor.
* The window is the half-open square [-L/2, L/2)^2, L = size_px * resolution_m. Cell
  (row iy, col ix) = (floor((y + L/2)/res), floor((x + L/2)/res)); raster layout (C, H, W).
* Channels (FHLD "Problem Definition"), all float32 in [0, 1], formulas below:
  0 mean intensity  mean of the per-sweep normalised intensity (normalize_intensity)
  1 density         log1p(count) / log1p(DENSITY_REF_COUNT), clipped
  2 height var.     population variance of z (m^2) / HEIGHT_VAR_REF_M2, clipped
  3 min height      (min z - MIN_HEIGHT_LOW_M) / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M), clipped
  Empty cells: channels 0-2 are 0 and min height is EMPTY_MIN_HEIGHT; density == 0 is the
  unambiguous "no points" marker.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

# --- normalisation constants: the exact channel formulas use these (see _Accumulator.encode) ---
INTENSITY_FULL_SCALES = (1.0, 255.0, 65535.0)  # 0-1 float, 8-bit / Velodyne, 16-bit sensors
INTENSITY_PERCENTILE = 99.9  # robust "max" of a sweep when picking its full scale
DENSITY_REF_COUNT = 16  # points per cell that saturate the density channel
HEIGHT_VAR_REF_M2 = 0.1  # variance (m^2) that saturates the height-variance channel
MIN_HEIGHT_LOW_M = -3.0  # min height mapped to 0 (road is about -1.5..-2 m below the sensor)
MIN_HEIGHT_HIGH_M = 1.0  # min height mapped to 1
EMPTY_MIN_HEIGHT = 1.0  # min-height channel of an empty cell: min of no points = +inf, clipped
HEIGHT_SHIFT_M = -1.8  # nominal road height: heights are summed relative to it (float32 sums)
Z_REBASE_M = 2.0  # the grid re-bases its height reference when the road moves this much
CHANNELS = ('mean_intensity', 'density', 'height_variance', 'min_height')


@dataclass(frozen=True)
class BevSpec:
    """Geometry of the BEV window: size_px x size_px square cells of resolution_m metres."""

    size_px: int = 640
    resolution_m: float = 0.04

    def __post_init__(self) -> None:
        if self.size_px <= 0 or not self.resolution_m > 0:
            raise ValueError(f'BevSpec needs size_px > 0 and resolution_m > 0, got {self}')

    @property
    def length_m(self) -> float:
        """Side of the square window in metres."""
        return self.size_px * self.resolution_m

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Window-frame metres (..., >=2) x, y[, z] -> continuous pixel coords (..., 2) col, row.

        Cell (row, col) covers [row, row + 1) x [col, col + 1); pixel centres are at k + 0.5.
        float32 input stays float32.
        """
        xy = np.asarray(xy)[..., :2]
        dtype = xy.dtype if xy.dtype == np.float32 else np.dtype(np.float64)
        return xy.astype(dtype, copy=False) * dtype.type(1.0 / self.resolution_m) \
            + dtype.type(self.size_px / 2)

    def pixel_to_world(self, colrow: np.ndarray) -> np.ndarray:
        """Continuous pixel coords (..., 2) (col, row) -> window-frame metres (..., 2) (x, y)."""
        colrow = np.asarray(colrow, dtype=np.float64)
        return (colrow - self.size_px / 2) * self.resolution_m


def min_height_m(raster: np.ndarray) -> np.ndarray:
    """(..., 4, H, W) raster -> (..., H, W) per-cell minimum height in metres, NaN where empty.

    The inverse of the min-height channel inside its clip range (heights outside
    [MIN_HEIGHT_LOW_M, MIN_HEIGHT_HIGH_M] come back clipped).
    """
    raster = np.asarray(raster)
    z = raster[..., 3, :, :] * (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M) + MIN_HEIGHT_LOW_M
    return np.where(raster[..., 1, :, :] > 0, z, np.nan)


def normalize_intensity(raw: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Raw intensity of one sweep -> float32 in [0, 1].

    With ``scale=None`` the full scale is the smallest of INTENSITY_FULL_SCALES (1, 255, 65535)
    that is >= the sweep's 99.9th percentile (the largest one if none is): 0-1 float sensors
    -> 1; Velodyne-style 0-255 floats and Ouster calibrated reflectivity (uint16 holding 0-255)
    -> 255; raw 16-bit signal -> 65535. The percentile ignores a few retro-reflector outliers,
    which are then clipped to 1. Pass ``scale`` to fix it for a sensor (e.g. from a parameter)
    so a dim sweep cannot switch scales. Non-finite values become 0.
    """
    values = np.asarray(raw, dtype=np.float32).reshape(-1)
    if scale is None:
        finite = values[np.isfinite(values)]
        robust_max = float(np.percentile(finite, INTENSITY_PERCENTILE)) if finite.size else 0.0
        scale = next((s for s in INTENSITY_FULL_SCALES if s >= robust_max),
                     INTENSITY_FULL_SCALES[-1])
    elif not scale > 0:
        raise ValueError(f'intensity scale must be > 0, got {scale}')
    out = values * np.float32(1.0 / scale)
    np.clip(out, 0.0, 1.0, out=out)
    out[~np.isfinite(out)] = 0.0  # clip keeps NaN
    return out


class _Scratch:
    """Work arrays reused across calls: fresh multi-megabyte temporaries cost page faults."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: int | tuple[int, ...], dtype: type) -> np.ndarray:
        size = math.prod(shape) if isinstance(shape, tuple) else shape
        buf = self._arrays.get(name)
        if buf is None or buf.shape[0] < size:
            buf = self._arrays[name] = np.empty(size + size // 4, dtype)  # growth headroom
        return buf[:size].reshape(shape)


def _window_affine(cos: float, sin: float, offset: np.ndarray, spec: BevSpec) -> np.ndarray:
    """(2, 3) float32 map [x, y, 1] -> bordered pixel coordinates (col + 1, row + 1).

    For points rotated by the window yaw (cos, sin), then shifted by offset (window metres).
    The accumulators have a one-cell border, hence the + 1.
    """
    inv, base = 1.0 / spec.resolution_m, spec.size_px / 2 + 1
    return np.array([[cos * inv, sin * inv, offset[0] * inv + base],
                     [-sin * inv, cos * inv, offset[1] * inv + base]], dtype=np.float32)


def _pixel_coords(xy: np.ndarray, affine: np.ndarray, out: np.ndarray,
                  tmp: np.ndarray) -> np.ndarray:
    """affine @ [x; y; 1] for xy (2, N) float32, into out (2, N). Elementwise on purpose: the
    threaded BLAS matmul stalled for milliseconds now and then on this busy 2-core machine."""
    x, y = xy
    for k in range(2):
        np.multiply(x, affine[k, 0], out=out[k])
        out[k] += np.multiply(y, affine[k, 1], out=tmp)
        out[k] += affine[k, 2]
    return out


def _pack_count_intensity(intensity01: np.ndarray) -> np.ndarray:
    """complex64 1 + i*intensity: one scatter-add then yields both count and intensity sum."""
    packed = np.empty(intensity01.shape[0], dtype=np.complex64)
    pairs = packed.view(np.float32).reshape(-1, 2)
    pairs[:, 0] = 1.0
    pairs[:, 1] = intensity01
    return packed


def _pack_heights(e: np.ndarray) -> np.ndarray:
    """complex64 e + i*e^2: one scatter-add yields both height sums."""
    packed = np.empty(e.shape[0], dtype=np.complex64)
    pairs = packed.view(np.float32).reshape(-1, 2)
    pairs[:, 0] = e
    np.multiply(e, e, out=pairs[:, 1])
    return packed


# density depends only on the count and saturates at DENSITY_REF_COUNT: a lookup table
_DENSITY_LUT = (np.log1p(np.arange(DENSITY_REF_COUNT + 1)) / math.log1p(DENSITY_REF_COUNT)
                ).astype(np.float32)


class _Accumulator:
    """Per-cell statistics of one window, in arrays reused across windows.

    The arrays have a one-cell border: points outside the window are clipped into it instead of
    being compacted away, so adding a sweep is a few elementwise passes and three ufunc.at
    scatters (numpy's fast path: matching dtypes, contiguous). Sums are float32 and packed in
    pairs as complex64: (count, intensity) and (e, e^2), heights e relative to a reference
    near the road (variance is shift-invariant; small e keeps E[e^2] - E[e]^2 accurate).
    """

    def __init__(self, spec: BevSpec) -> None:
        self.spec = spec
        side = spec.size_px + 2
        self.count_intensity = np.zeros(side * side, dtype=np.complex64)
        self.heights = np.zeros(side * side, dtype=np.complex64)
        self.e_min = np.full(side * side, np.inf, dtype=np.float32)
        self.scratch = _Scratch()

    def clear(self) -> None:
        self.count_intensity.fill(0)
        self.heights.fill(0)
        self.e_min.fill(np.inf)

    def add(self, xy: np.ndarray, affine: np.ndarray, count_intensity: np.ndarray,
            heights: np.ndarray, e: np.ndarray) -> None:
        """Add points: xy (2, N) float32 mapped to pixels by affine (2, 3); count_intensity =
        1 + i*intensity and heights = e + i*e^2 (complex64), e = z - z_ref (float32)."""
        n, side, get = xy.shape[1], self.spec.size_px + 2, self.scratch.get
        pix = _pixel_coords(xy, affine, get('pix', (2, n), np.float32), get('tmp', n, np.float32))
        np.clip(pix, 0, side - 1, out=pix)  # outside the window -> the border cells
        cells = get('cells', (2, n), np.intp)
        np.copyto(cells, pix, casting='unsafe')  # non-negative: trunc == floor
        flat = cells[1]
        flat *= side
        flat += cells[0]
        np.add.at(self.count_intensity, flat, count_intensity)
        np.add.at(self.heights, flat, heights)
        np.minimum.at(self.e_min, flat, e)

    def encode(self, z_ref: float) -> np.ndarray:
        """The (4, H, W) float32 raster of the points added since clear(); z = e + z_ref.

        Formulas per cell with n points: mean intensity = sum(i) / n; density =
        min(log1p(n) / log1p(DENSITY_REF_COUNT), 1); height variance = clip((sum(e^2) / n -
        (sum(e) / n)^2) / HEIGHT_VAR_REF_M2, 0, 1); min height = clip((min z - LOW) / (HIGH -
        LOW), 0, 1). For n = 0 the sums are 0 (channels 0-2 are 0) and min z is +inf, so the
        min height saturates at 1 (EMPTY_MIN_HEIGHT).
        """
        size, f32, get = self.spec.size_px, np.float32, self.scratch.get
        inner = (slice(1, size + 1), slice(1, size + 1))
        count_intensity = self.count_intensity.reshape(size + 2, -1)[inner]
        heights = self.heights.reshape(size + 2, -1)[inner]
        raster = np.empty((4, size, size), dtype=f32)
        # 1 / n; 1e30 for empty cells, whose sums are 0 (counts are whole numbers, so adding
        # 1e-30 changes no other cell)
        inv_n = np.add(count_intensity.real, f32(1e-30), out=get('inv_n', (size, size), f32))
        np.divide(f32(1.0), inv_n, out=inv_n)
        np.multiply(count_intensity.imag, inv_n, out=raster[0])
        # density = LUT[min(n, REF)], the LUT holding log1p(k) / log1p(REF); 'clip' is the min
        count = get('count', (size, size), np.intp)
        np.copyto(count, count_intensity.real, casting='unsafe')
        np.take(_DENSITY_LUT, count, out=raster[1], mode='clip')
        mean_sq = np.multiply(heights.real, inv_n, out=get('mean_sq', (size, size), f32))
        mean_sq *= mean_sq
        var = np.multiply(heights.imag, inv_n, out=raster[2])
        var -= mean_sq
        var *= f32(1.0 / HEIGHT_VAR_REF_M2)
        np.clip(var, 0.0, 1.0, out=var)
        scale = 1.0 / (MIN_HEIGHT_HIGH_M - MIN_HEIGHT_LOW_M)
        z_min = np.multiply(self.e_min.reshape(size + 2, -1)[inner], f32(scale), out=raster[3])
        z_min += f32((z_ref - MIN_HEIGHT_LOW_M) * scale)
        np.clip(z_min, 0.0, 1.0, out=z_min)  # empty: +inf -> 1
        return raster


def rasterize(xyz_window: np.ndarray, intensity01: np.ndarray,
              spec: BevSpec = BevSpec()) -> np.ndarray:
    """Points (N, 3) in the window frame + intensities in [0, 1] -> float32 raster (4, H, W).

    Points outside the window or with a non-finite coordinate/intensity are ignored.
    """
    xyz = np.asarray(xyz_window, dtype=np.float32).reshape(-1, 3)
    inten = np.asarray(intensity01, dtype=np.float32).reshape(-1)
    if inten.shape[0] != xyz.shape[0]:
        raise ValueError(f'{xyz.shape[0]} points but {inten.shape[0]} intensities')
    keep = np.isfinite(xyz).all(axis=1) & np.isfinite(inten)
    xyz, inten = xyz[keep], inten[keep]
    e = xyz[:, 2] - np.float32(HEIGHT_SHIFT_M)
    acc = _Accumulator(spec)
    acc.add(np.ascontiguousarray(xyz[:, :2].T), _window_affine(1.0, 0.0, np.zeros(3), spec),
            _pack_count_intensity(inten), _pack_heights(e), e)
    return acc.encode(HEIGHT_SHIFT_M)


def yaw_frame(sensor_to_output: np.ndarray) -> np.ndarray:
    """Gravity-aligned pose: sensor position, yaw of its x axis, roll/pitch dropped."""
    yaw = math.atan2(sensor_to_output[1, 0], sensor_to_output[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    frame = np.eye(4)
    frame[:2, :2] = [[c, -s], [s, c]]
    frame[:3, 3] = sensor_to_output[:3, 3]
    return frame


@dataclass(frozen=True)
class _Sweep:
    """One sweep as stored: output-frame axes, float32 offsets from float64 references, so
    millimetres survive however far the vehicle is from the odometry origin."""

    stamp_ns: int
    pose: np.ndarray  # (4, 4) float64 sensor -> output
    xy: np.ndarray  # (2, N) float32 rows x - pose x, y - pose y
    e: np.ndarray  # (N,) float32 z - z_ref
    z_ref: float  # output-frame height that e is relative to (shared by the grid's sweeps)
    count_intensity: np.ndarray  # (N,) complex64 1 + i*intensity01
    heights: np.ndarray  # (N,) complex64 e + i*e^2

    def with_z_ref(self, z_ref: float) -> _Sweep:
        e = self.e + np.float32(self.z_ref - z_ref)
        return _Sweep(self.stamp_ns, self.pose, self.xy, e, z_ref, self.count_intensity,
                      _pack_heights(e))


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
            pix = _pixel_coords(sweep.xy, affine, np.empty_like(sweep.xy),
                                np.empty_like(sweep.e))  # exactly as rasterised
            keep = ((pix >= 1) & (pix < size + 1)).all(axis=0)
            xy = self.spec.pixel_to_world(pix[:, keep].T - 1.0)
            xyz.append(np.column_stack([xy, sweep.e[keep] + self._e_to_z]).astype(np.float32))
            inten.append(sweep.count_intensity.imag[keep])
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
                 max_sweeps: int = 10) -> None:
        if not accumulate_sec >= 0 or max_sweeps < 1:
            raise ValueError('RollingBevGrid needs accumulate_sec >= 0 and max_sweeps >= 1')
        self.spec = spec
        self.accumulate_ns = round(accumulate_sec * 1e9)
        self.max_sweeps = int(max_sweeps)
        self._sweeps: deque[_Sweep] = deque()
        self._acc = _Accumulator(spec)

    def __len__(self) -> int:
        return len(self._sweeps)

    def reset(self) -> None:
        self._sweeps.clear()

    @property
    def newest_stamp_ns(self) -> int | None:
        return self._sweeps[-1].stamp_ns if self._sweeps else None

    def insert(self, stamp_ns: int, xyz_sensor: np.ndarray, intensity_raw: np.ndarray,
               sensor_to_output: np.ndarray, intensity_scale: float | None = None) -> bool:
        """Add one sweep: sensor-frame points and the sensor pose at the sweep stamp.

        Use the identity pose without odometry. Points with a non-finite coordinate or
        intensity are dropped. Returns True if the grid was reset (stamp older than newest).
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
            x, y, z, raw = x[finite], y[finite], z[finite], raw[finite]
        z_ref = self._z_ref_for(pose[2, 3])
        # rotate into output-frame axes (elementwise, as in _pixel_coords)
        rot = pose[:3, :3].astype(np.float32)
        out = np.empty((3, x.shape[0]), dtype=np.float32)  # rows x, y, e
        for k in range(3):
            np.multiply(x, rot[k, 0], out=out[k])
            out[k] += y * rot[k, 1]
            out[k] += z * rot[k, 2]
        e = out[2]
        e += np.float32(pose[2, 3] - z_ref)
        self._sweeps.append(_Sweep(stamp_ns, pose, out[:2], e, z_ref, _pack_count_intensity(
            normalize_intensity(raw, intensity_scale)), _pack_heights(e)))
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

    def window(self) -> BevWindow | None:
        """Raster of the window centred on the newest sensor pose (None when no sweep is held)."""
        if not self._sweeps:
            return None
        spec, newest = self.spec, self._sweeps[-1]
        window_to_output = yaw_frame(newest.pose)
        rot, origin = window_to_output[:3, :3], window_to_output[:3, 3]  # window axes in output
        self._acc.clear()
        sources = []
        for sweep in self._sweeps:
            offset = (sweep.pose[:3, 3] - origin) @ rot  # the sweep's sensor origin, window frame
            affine = _window_affine(rot[0, 0], rot[1, 0], offset, spec)
            self._acc.add(sweep.xy, affine, sweep.count_intensity, sweep.heights, sweep.e)
            sources.append((sweep, affine))
        e_to_z = newest.z_ref - origin[2]
        half = spec.length_m / 2
        corners = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0],
                            [-half, half, 0.0], [-half, -half, 0.0]])
        return BevWindow(self._acc.encode(e_to_z), newest.stamp_ns, window_to_output,
                         corners @ rot.T + origin, spec, tuple(sources), e_to_z)


def synthetic_sweep(rng: np.random.Generator, beams: int = 64,
                    columns: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """A beams x columns spinning-LiDAR sweep of a street canyon (benchmarks and tests).

    Ground at z = -1.8 m below the sensor, walls at |y| = 7 m, far returns capped at 80 m;
    intensity 0-255 with bright 15 cm lane stripes at y = +-1.75 m.
    """
    elev = np.deg2rad(np.linspace(-25.0, 15.0, beams))[:, None]
    azim = np.linspace(-np.pi, np.pi, columns, endpoint=False)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim),
                                     np.sin(elev)), axis=-1).reshape(-1, 3)
    with np.errstate(divide='ignore'):
        t_ground = np.where(d[:, 2] < 0, -1.8 / d[:, 2], np.inf)
        t_wall = np.where(d[:, 1] != 0, 7.0 / np.abs(d[:, 1]), np.inf)
    r = np.minimum(np.minimum(t_ground, t_wall), 80.0) + rng.normal(0, 0.01, d.shape[0])
    xyz = (d * r[:, None]).astype(np.float32)
    on_stripe = (np.abs(np.abs(xyz[:, 1]) - 1.75) < 0.075) & (xyz[:, 2] < -1.7)
    intensity = np.where(on_stripe, 180.0, 20.0) + rng.uniform(0, 15, d.shape[0])
    return xyz, intensity.astype(np.float32)


def bench_bev() -> dict[str, float]:
    """`fhld bench bev`: 64x1024 sweeps at 10 Hz, 10 accumulated, ego at 10 m/s turning."""
    from fhld_ros.bench import time_median

    rng = np.random.default_rng(0)
    sweeps = [synthetic_sweep(rng) for _ in range(4)]
    grid = RollingBevGrid(BevSpec(), accumulate_sec=1.0, max_sweeps=10)
    state = {'k': 0}

    def insert() -> None:
        k = state['k'] = state['k'] + 1
        yaw = 0.02 * k
        pose = np.eye(4)
        pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        pose[:2, 3] = [1000.0 + k, 2000.0 + 0.1 * k]
        xyz, inten = sweeps[k % len(sweeps)]
        grid.insert(k * 100_000_000, xyz, inten, pose)

    for _ in range(10):
        insert()
    insert_ms = time_median(insert, repeats=30, warmup=2)
    raster_ms = time_median(grid.window, repeats=20, warmup=2)
    window = grid.window()
    return {'grid_insert_ms': insert_ms, 'raster_ms': raster_ms,
            'raster_points': float(window.points_window.shape[0]),
            'grid_points': float(sum(s.e.shape[0] for s in grid._sweeps))}
