"""Multi-beam LiDAR: sensor presets, return/intensity model and driver point layouts.

Presets follow the published vertical angle sets of common spinning sensors (Velodyne VLP-16/
VLP-32C/HDL-32E/HDL-64E, Ouster OS1/OS2), plus a forward-only scanner with a 70 degree field of
view. Returns follow a simple radiometric model: apparent reflectance = diffuse part (rough
surfaces: rho * sqrt(cos incidence)) + retro-reflective part (glass-bead paint, weakly incidence
dependent); detection probability falls with reflectance / range^2 so dark and grazing far
ground fades out as on real sensors. Outputs use the layouts of the Ouster driver (organised,
padded 48-byte points, zero or NaN no-returns, `t` in ns, calibrated uint16 `reflectivity`) or
the Velodyne driver (unorganised XYZIRT).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LAYOUTS = ('ouster', 'velodyne')
INTENSITY_SCALES = ('reflectivity', 'float', 'u8')  # uint16 calibrated, 0-1 float, 0-255 float
NO_RETURNS = ('zero', 'nan')

_VLP32C = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667,
           -3.333, -3.0, -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0,
           0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0)
# HDL-64E: upper block +2 .. -8.33 at 1/3 deg, lower block -8.83 .. -24.33 at 1/2 deg
_HDL64 = tuple(np.round(np.concatenate([2.0 - np.arange(32) / 3.0,
                                        -8.83 - 0.5 * np.arange(32)]), 3))
# Hesai Pandar64: 0.167 deg apart from +1.86 to -6.06, sparse above and below (the real
# PJLab sweeps' ground rings fall on these angles to 0.01 deg)
_PANDAR64 = (14.882, 11.032, 8.059, 5.057, 3.04, 2.028) + tuple(
    np.round(1.86 - np.arange(48) * (7.921 / 47), 3)) + (
    -7.063, -8.059, -9.06, -9.885, -11.032, -12.006, -12.974, -13.93, -18.889, -24.897)


@dataclass(frozen=True)
class SensorPreset:
    name: str
    elevations_deg: tuple[float, ...]
    columns: int  # per revolution at 10 Hz
    layout: str
    intensity: str
    max_range: float
    r10: float  # range where a 10 % Lambertian target at normal incidence is seen half the time
    sigma0: float  # range noise (m) = sigma0 + sigma_k * range
    sigma_k: float
    gain_sigma: float  # per-beam intensity gain spread (uncalibrated sensors stripe)
    mount_z: float = 1.95  # height above ground
    azimuth_fov_deg: float = 360.0  # < 360: a forward-only scanner, no returns outside it

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)


def _uniform(lo: float, hi: float, n: int) -> tuple[float, ...]:
    return tuple(np.round(np.linspace(lo, hi, n), 4))


SENSORS: dict[str, SensorPreset] = {p.name: p for p in (
    SensorPreset('vlp16', _uniform(-15, 15, 16), 1800, 'velodyne', 'u8', 100, 45, 0.02, 2e-4,
                 0.08),
    SensorPreset('vlp32c', _VLP32C, 1800, 'velodyne', 'u8', 200, 70, 0.02, 2e-4, 0.08),
    SensorPreset('hdl32e', _uniform(-30.67, 10.67, 32), 2048, 'velodyne', 'u8', 100, 50, 0.02,
                 2e-4, 0.1),
    SensorPreset('hdl64e', _HDL64, 2048, 'velodyne', 'u8', 120, 60, 0.02, 2e-4, 0.1,
                 mount_z=1.9),
    SensorPreset('os1-32', _uniform(-22.5, 22.5, 32), 1024, 'ouster', 'reflectivity', 120, 50,
                 0.015, 2e-4, 0.02),
    SensorPreset('os1-64', _uniform(-16.6, 16.6, 64), 1024, 'ouster', 'reflectivity', 120, 55,
                 0.015, 2e-4, 0.02),
    SensorPreset('os1-128', _uniform(-22.5, 22.5, 128), 1024, 'ouster', 'reflectivity', 120, 55,
                 0.015, 2e-4, 0.02),
    SensorPreset('os2-128', _uniform(-11.25, 11.25, 128), 1024, 'ouster', 'reflectivity', 240,
                 110, 0.025, 2e-4, 0.02),
    # Forward-only solid-state scanner (Livox-like, ~70 x 77 degree field of view), modelled
    # as a dense grid clipped to its field of view; its non-repetitive pattern is not modelled.
    SensorPreset('forward70', _uniform(-38.6, 38.6, 64), 2048, 'velodyne', 'u8', 190, 60,
                 0.02, 2e-4, 0.05, azimuth_fov_deg=70.4),
    # Real sensors of the development sweeps: the Hesai Pandar64 (PJLab) and nuScenes' roof
    # HDL-32E at 1.84 m, whose uncalibrated lasers read whole rings 2-3 x brighter.
    SensorPreset('pandar64', _PANDAR64, 1800, 'velodyne', 'u8', 200, 60, 0.02, 2e-4, 0.1),
    SensorPreset('hdl32e-nuscenes', _uniform(-30.67, 10.67, 32), 1085, 'velodyne', 'u8', 70,
                 40, 0.02, 2e-4, 0.3, mount_z=1.84),
)}
# The presets the test set and `sensors: all` cycle through, fixed so that the test set stays
# the same windows when presets are added.
SPINNING = ('vlp16', 'vlp32c', 'hdl32e', 'hdl64e', 'os1-32', 'os1-64', 'os1-128', 'os2-128')
DEFAULT_SENSOR = 'os1-64'


def local_directions(elev_sorted: np.ndarray, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (B, W, 3) in the sensor frame and the column azimuths (W,).

    Columns fire clockwise starting behind the sensor, as in Ouster's destaggered image: the
    middle column looks forward (+x)."""
    az = np.pi - 2.0 * np.pi * (np.arange(columns) + 0.5) / columns
    el = elev_sorted[:, None]
    dirs = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                        np.sin(el)), axis=-1)
    return dirs, az


@dataclass
class Returns:
    """Radiometry of the hits of one sweep, (B, W) each."""

    rho: np.ndarray  # diffuse reflectance
    retro: np.ndarray  # retro-reflective strength (paint beads), 0 elsewhere
    cos: np.ndarray  # |cos incidence|
    t: np.ndarray  # true range, inf for no hit


def detect_and_measure(ret: Returns, preset: SensorPreset, scale: str, gains: np.ndarray,
                       rng: np.random.Generator | None, dropout: float = 0.005
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(valid, measured range, intensity value in the output scale) per ray, (B, W) each.

    rng None: noise-free (no range/intensity noise, detection thresholded at p = 0.5)."""
    shape = ret.t.shape
    hit = np.flatnonzero((np.isfinite(ret.t) & (ret.t <= preset.max_range)).ravel())
    valid = np.zeros(shape, dtype=bool)
    r_out = np.zeros(shape)
    value = np.zeros(shape, dtype=np.float32)
    r = ret.t.ravel()[hit]
    f32 = np.float32  # radiometry needs no double precision
    cos = np.clip(ret.cos.ravel()[hit].astype(f32), f32(0.02), f32(1.0))
    a_d = ret.rho.ravel()[hit].astype(f32) * np.sqrt(cos)
    a_r = ret.retro.ravel()[hit].astype(f32) * np.sqrt(f32(0.35) + f32(0.65) * cos)
    ratio = f32(preset.r10) / np.maximum(r.astype(f32), f32(0.5))
    snr = (a_d + a_r) * f32(10.0) * ratio * ratio
    snr3 = snr * snr * snr
    p = snr3 / (f32(1.0) + snr3)
    gain = np.broadcast_to(gains[:, None], shape).ravel()[hit]
    if rng is None:
        keep = p > 0.5
        r_meas, noise_mul, noise_add = r, 1.0, 0.0
    else:
        keep = rng.random(hit.size, dtype=np.float32) < p * (1.0 - dropout)  # + dropouts
        normal = rng.standard_normal((3, hit.size), dtype=np.float32)
        sigma = (preset.sigma0 + preset.sigma_k * r) * (1.0 + 0.5 / np.sqrt(snr + 1e-6))
        r_meas = r + normal[0] * sigma
        noise_mul = np.exp(0.08 * normal[1])
        noise_add = normal[2]
    if scale == 'reflectivity':  # calibrated: range compensated, 0-100 diffuse, > 100 retro
        v = (100.0 * a_d + 155.0 * a_r) * gain * noise_mul + 1.5 * noise_add
        v = np.clip(np.round(v), 0, 255)
    else:  # raw-ish intensity: saturating response with residual range falloff
        falloff = 1.0 / (1.0 + (r / 30.0) ** 1.5)
        i01 = 1.0 - np.exp(-(a_d + 1.5 * a_r) * falloff * gain * noise_mul / 0.8)
        i01 = np.clip(i01 + 0.005 * noise_add, 0.0, 1.0)
        v = np.round(255.0 * i01) if scale == 'u8' else i01
    valid.ravel()[hit] = keep
    r_out.ravel()[hit] = r_meas
    value.ravel()[hit] = v
    return valid, r_out, value


def ouster_dtype(scale: str) -> np.dtype:
    """ouster_ros point layout (48-byte points, x y z padded to 16, t ns, ring, range mm)."""
    fields = [('x', '<f4', 0), ('y', '<f4', 4), ('z', '<f4', 8)]
    if scale == 'reflectivity':
        fields.append(('reflectivity', '<u2', 24))
    else:
        fields.append(('intensity', '<f4', 16))
    fields += [('t', '<u4', 20), ('ring', '<u2', 26), ('range', '<u4', 32)]
    fields.sort(key=lambda f: f[2])
    return np.dtype({'names': [f[0] for f in fields], 'formats': [f[1] for f in fields],
                     'offsets': [f[2] for f in fields], 'itemsize': 48})


def velodyne_dtype(scale: str) -> np.dtype:
    """velodyne_pointcloud XYZIRT layout (packed 22-byte points; time in s from the stamp)."""
    if scale == 'reflectivity':
        return np.dtype({'names': ['x', 'y', 'z', 'reflectivity', 'ring', 'time'],
                         'formats': ['<f4', '<f4', '<f4', '<u2', '<u2', '<f4'],
                         'offsets': [0, 4, 8, 12, 14, 16], 'itemsize': 20})
    return np.dtype({'names': ['x', 'y', 'z', 'intensity', 'ring', 'time'],
                     'formats': ['<f4', '<f4', '<f4', '<f4', '<u2', '<f4'],
                     'offsets': [0, 4, 8, 12, 16, 18], 'itemsize': 22})


def pack_points(layout: str, scale: str, no_return: str, xyz: np.ndarray, valid: np.ndarray,
                value: np.ndarray, r_meas: np.ndarray, col_time_s: np.ndarray
                ) -> tuple[np.ndarray, int, np.ndarray]:
    """Arrays (B, W, ...) with beams ascending -> (structured points, cloud height, index).

    index maps each output point to its flat (B, W) ray index (-1 for padding no-returns are
    still mapped: organised clouds keep every ray)."""
    nb, nw = valid.shape
    if layout == 'ouster':  # row 0 is the top beam
        order = np.arange(nb * nw).reshape(nb, nw)[::-1].ravel()
        pts = np.zeros(nb * nw, dtype=ouster_dtype(scale))
        v = valid.ravel()[order]
        fill = np.nan if no_return == 'nan' else 0.0
        for k, name in enumerate('xyz'):
            pts[name] = np.where(v, xyz[..., k].ravel()[order], fill)
        field = 'reflectivity' if scale == 'reflectivity' else 'intensity'
        pts[field] = np.where(v, value.ravel()[order], 0)
        pts['t'] = np.broadcast_to(np.round(col_time_s * 1e9).astype(np.uint32),
                                   (nb, nw)).ravel()
        pts['ring'] = np.repeat(np.arange(nb, dtype=np.uint16), nw)
        pts['range'] = np.where(v, np.round(r_meas.ravel()[order] * 1000.0), 0).astype(np.uint32)
        return pts, nb, order
    # velodyne: valid points only, in firing order (column by column, rings ascending)
    order = np.arange(nb * nw).reshape(nb, nw).T.ravel()
    order = order[valid.ravel()[order]]
    pts = np.zeros(order.size, dtype=velodyne_dtype(scale))
    for k, name in enumerate('xyz'):
        pts[name] = xyz[..., k].ravel()[order]
    field = 'reflectivity' if scale == 'reflectivity' else 'intensity'
    pts[field] = value.ravel()[order]
    pts['ring'] = order // nw
    pts['time'] = np.broadcast_to(col_time_s, (nb, nw)).ravel()[order]
    return pts, 1, order
