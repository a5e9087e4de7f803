"""What real sensors and roads vary, drawn per training seed (CacheSettings.sensor_variation).

Each option draws from its own fixed place in the seed's random stream, so a share or option
added later leaves every earlier draw where it was: a larger share only changes more seeds the
same way. The shares a cache was built with are recorded in its index (variation_record).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from fhld_ros.sim.lidar import INTENSITY_SCALES

# below ~1.6x, worn simulated paint is lost in the asphalt's own patches (+-25 %), and lanes
# taught there were drawn on unmarked roads too (docs/training.md)
WORN_PAINT_RANGE = (1.6, 8.0)
WORN_PAINT_SHARE = 0.6
NO_MARKINGS_SHARE = 0.2
SINGLE_SWEEP_SHARE = 0.2
BRIGHT_ASPHALT_RANGE = (0.16, 0.32)  # KITTI-like pavement (the usual one: 0.07-0.14)
GUTTER_RATIO_RANGE = (0.6, 2.5)  # a light or dark strip along the curbs, x the pavement
MOUNT_TILT_DEG = 3.0
ROAD_LOOK_SHARE = 0.35  # each of bright pavement, gutters and seams on this share of seeds
# with every simulated marked road painting a line just inside its curbs, the model learnt
# "curb => lane line" and drew lanes along bare real curbs (docs/training.md)
BARE_CURB_SHARE = 0.5
# uncalibrated multi-laser sensors (per-laser gain, whole bright rings): with laser_gains, this
# share of the seeds draws each laser's gain log-normal with a sigma in LASER_GAIN_SIGMA_RANGE
LASER_GAIN_SHARE = 0.5
LASER_GAIN_SIGMA_RANGE = (0.15, 0.3)
# CacheSettings fields that set how the seeds vary (a share of them, the worn paint's
# brightest), recorded in the cache index under 'variation', and their defaults
SHARES = {'no_markings_share': NO_MARKINGS_SHARE, 'single_sweep_share': SINGLE_SWEEP_SHARE,
          'bright_asphalt_share': ROAD_LOOK_SHARE, 'worn_paint_share': WORN_PAINT_SHARE,
          'worn_paint_max': WORN_PAINT_RANGE[1]}


class VariationOptions(Protocol):
    """The options a cache's settings (data/cache.py CacheSettings) give the draws below."""

    no_markings_share: float
    single_sweep_share: float
    bright_asphalt_share: float
    worn_paint_share: float
    worn_paint_max: float
    road_look: bool
    bare_curbs: bool
    laser_gains: bool


def sensor_variation(seed: int, settings: VariationOptions) -> dict:
    """What real sensors and roads vary, drawn per training seed (settings: which options):

    * paint: worn_paint_share of the roads worn, beads gone, reflectance WORN_PAINT_RANGE's
      low end to worn_paint_max x the asphalt's (log-uniform); else fresh retro-reflective
      paint (~15-20x); no_markings_share of the roads carry no paint at all
    * units: 1/4 each the preset's own, uint16 reflectivity, 0-1 float, 0-255 counts
    * gain: half the seeds x0.25-x4 (log-uniform; integer counts round and saturate)
    * mount: half the seeds 1.4-2.5 m above the road instead of the preset's height
    * single_sweep_share of the seeds: windows of one sweep without odometry (the cloud frame,
      as the node runs without /odom), ending where the accumulated windows would
    * with road_look (sim.scene.RoadLook): KITTI-like bright pavement on bright_asphalt_share
      of the seeds, gutters along the paved edges and sealed seams and joints each on
      ROAD_LOOK_SHARE; half the seeds: the sensor tilted up to MOUNT_TILT_DEG in pitch and roll
    * with bare_curbs, BARE_CURB_SHARE of the seeds: no edge lines (the lanes run to the curb;
      its own stream of draws, so the draws above stay put)
    * with laser_gains, LASER_GAIN_SHARE of the seeds: per-laser gains log-normal with a sigma
      in LASER_GAIN_SIGMA_RANGE (its own stream too)
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E75]))
    worn = rng.random() < settings.worn_paint_share
    contrast = _log_uniform(rng, WORN_PAINT_RANGE[0], settings.worn_paint_max)
    units = (None, *INTENSITY_SCALES)[int(rng.integers(4))]
    gain = _log_uniform(rng, 0.25, 4.0) if rng.random() < 0.5 else 1.0
    mount = round(float(rng.uniform(1.4, 2.5)), 3) if rng.random() < 0.5 else None
    return {'paint_contrast': round(contrast, 3) if worn else None,
            'markings': bool(rng.random() >= settings.no_markings_share), 'intensity': units,
            'intensity_gain': round(gain, 3), 'mount_z': mount,
            'single_sweep': bool(rng.random() < settings.single_sweep_share),
            **(_road_look(rng, settings.bright_asphalt_share) if settings.road_look else {}),
            **(_bare_curbs(seed) if settings.bare_curbs else {}),
            **(_laser_gains(seed) if settings.laser_gains else {})}


def variation_record(settings: VariationOptions) -> dict:
    """The cache index's record of what shaped its shards besides the settings' own fields.

    A share at its default is recorded as before it was a setting, so older caches stay valid.
    """
    record = {'worn_paint_range': [WORN_PAINT_RANGE[0], settings.worn_paint_max],
              'no_markings_share': settings.no_markings_share,
              'single_sweep_share': settings.single_sweep_share}
    if settings.worn_paint_share != WORN_PAINT_SHARE:
        record['worn_paint_share'] = settings.worn_paint_share
    if settings.road_look:
        record.update(bright_asphalt_range=list(BRIGHT_ASPHALT_RANGE),
                      gutter_ratio_range=list(GUTTER_RATIO_RANGE), mount_tilt_deg=MOUNT_TILT_DEG,
                      road_look_share=ROAD_LOOK_SHARE)
        if settings.bright_asphalt_share != ROAD_LOOK_SHARE:
            record['bright_asphalt_share'] = settings.bright_asphalt_share
    if settings.bare_curbs:
        record['bare_curb_share'] = BARE_CURB_SHARE
    if settings.laser_gains:
        record.update(laser_gain_share=LASER_GAIN_SHARE,
                      laser_gain_sigma_range=list(LASER_GAIN_SIGMA_RANGE))
    return record


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def road_variation(seed: int) -> dict:
    """sensor_variation's pavement draws (road_look: bright pavement, gutters, seams; and
    bare_curbs) at their default shares, for a camera's drive: its own stream, so the seed's
    other draws stay put."""
    look = _road_look(np.random.default_rng(np.random.SeedSequence([seed, 0xCA3E])),
                      ROAD_LOOK_SHARE)
    return {**{key: look[key] for key in ('asphalt_rho', 'gutter_ratio', 'seams')},
            **_bare_curbs(seed)}


def _road_look(rng: np.random.Generator, bright_share: float) -> dict:
    """sensor_variation's pavement and mount draws (after its older ones, which stay put)."""
    bright = rng.random() < bright_share
    asphalt = round(_log_uniform(rng, *BRIGHT_ASPHALT_RANGE), 3)
    gutter = rng.random() < ROAD_LOOK_SHARE
    ratio = round(_log_uniform(rng, *GUTTER_RATIO_RANGE), 3)
    seams = bool(rng.random() < ROAD_LOOK_SHARE)
    tilt = rng.uniform(-MOUNT_TILT_DEG, MOUNT_TILT_DEG, 2) * (rng.random() < 0.5)
    return {'asphalt_rho': asphalt if bright else None, 'gutter_ratio': ratio if gutter else None,
            'seams': seams, 'mount_pitch_deg': round(float(tilt[0]), 2) + 0.0,
            'mount_roll_deg': round(float(tilt[1]), 2) + 0.0}


def _bare_curbs(seed: int) -> dict:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xC0B5]))
    return {'edge_lines': bool(rng.random() >= BARE_CURB_SHARE)}


def _laser_gains(seed: int) -> dict:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6A15]))
    sigma = rng.uniform(*LASER_GAIN_SIGMA_RANGE) if rng.random() < LASER_GAIN_SHARE else None
    return {'laser_gain_sigma': None if sigma is None else round(float(sigma), 3)}
