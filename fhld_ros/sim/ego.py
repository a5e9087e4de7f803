"""Ego motion: speed profile, lane following with lane changes, sensor poses, odometry drift.

The plan is made once for the whole run on a fine time grid: s(t) integrates the speed, the
lateral offset d(t) follows the current lane's centre and blends into the neighbouring lane
during a lane change (quintic blend over 3-6 s). Lanes that end (drops, merges, exit lanes)
are left in time. Poses sit on the road plane, pitched by the grade and rolled by the bank.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fhld_ros.sim.layout import Layout
from fhld_ros.sim.road import ReferenceLine, smoothstep

PLAN_DT = 0.05  # s


def rotation_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1)], -2)


@dataclass
class EgoPlan:
    times: np.ndarray  # (T,) plan grid (s)
    s: np.ndarray  # (T,)
    d: np.ndarray  # (T,)
    speed: np.ndarray  # (T,)
    lane_changes: list[tuple[float, float, int, int]]  # (t_start, t_end, from slot, to slot)

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, d, speed) at times t by linear interpolation."""
        return (np.interp(t, self.times, self.s), np.interp(t, self.times, self.d),
                np.interp(t, self.times, self.speed))


def speed_profile(rng: np.random.Generator, v0: float, times: np.ndarray) -> np.ndarray:
    """Gentle speed variation around v0 (bounded to 0-30 m/s; v0 = 0 stays at rest)."""
    if v0 <= 0:
        return np.zeros_like(times)
    amp = rng.uniform(0.0, 0.12) * v0
    period = rng.uniform(20.0, 60.0)
    v = v0 + amp * np.sin(2 * np.pi * times / period + rng.uniform(0, 2 * np.pi))
    return np.clip(v, 0.0, 30.0)


def _choices(layout: Layout, row_now: int, row_ahead: int) -> list[int]:
    """Ego-direction through lanes drivable from now to the look-ahead row."""
    out = []
    for k in layout.lane_indices(1):
        if layout.slots[k].dotted:  # exit / taper lanes: the ego keeps to through lanes
            continue
        if layout.drivable(k)[row_now:row_ahead + 1].all():
            out.append(k)
    return out


def plan_ego(rng: np.random.Generator, layout: Layout, duration: float, v0: float,
             s_start: float = 0.0) -> EgoPlan:
    """Lane following with random and forced lane changes."""
    times = np.arange(0.0, duration + 2 * PLAN_DT, PLAN_DT)
    speed = speed_profile(rng, v0, times)
    s = s_start + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * PLAN_DT)])
    centres = {k: layout.lane_centre(k) for k in layout.lane_indices(1)}
    rows = layout.row(s)

    def look(i: int) -> int:
        return int(layout.row(s[i] + 40.0 + 6.0 * speed[i]))

    options = _choices(layout, rows[0], look(0)) or layout.lane_indices(1)
    lane = options[int(rng.integers(len(options)))]
    # d = (1 - beta) * centre[lane_a] + beta * centre[lane_b]; beta ramps during a change
    lane_a = np.full(times.size, lane)
    lane_b = np.full(times.size, lane)
    beta = np.ones(times.size)
    changes = []
    decide_every = int(round(0.5 / PLAN_DT))
    next_voluntary = rng.exponential(15.0)
    i = 0
    while i < times.size - 1:
        i += 1
        if i % decide_every or speed[i] < 1.0:
            continue
        ahead = _choices(layout, rows[i], look(i))
        forced = lane not in ahead
        if not (forced or times[i] >= next_voluntary):
            continue
        next_voluntary = times[i] + 6.0 + rng.exponential(15.0)
        here = centres[lane][rows[i]]
        near = [k for k in ahead if k != lane and abs(centres[k][rows[i]] - here) < 4.5]
        if not near:  # adjacent lanes only
            continue
        target = near[int(rng.integers(len(near)))]
        dur = rng.uniform(3.0, 6.0)
        j = min(times.size, i + int(dur / PLAN_DT))
        lane_a[i:], lane_b[i:] = lane, target
        beta[i:j] = smoothstep((times[i:j] - times[i]) / dur)
        beta[j:] = 1.0
        changes.append((float(times[i]), float(times[i] + dur), int(lane), int(target)))
        lane, i = target, j
    centre = np.array([centres[k] for k in layout.lane_indices(1)])
    index = {k: n for n, k in enumerate(layout.lane_indices(1))}
    ca = centre[[index[k] for k in lane_a], rows]
    cb = centre[[index[k] for k in lane_b], rows]
    d = (1.0 - beta) * ca + beta * cb
    return EgoPlan(times, s, d, speed, changes)


@dataclass(frozen=True)
class Mount:
    """Sensor position on the ego (base frame: on the ground below the vehicle centre)."""

    x: float = 0.3
    z: float = 1.95
    pitch: float = 0.0  # mounting error of the sensor against the vehicle (rad)
    roll: float = 0.0


def poses(ref: ReferenceLine, plan: EgoPlan, t: np.ndarray, mount: Mount) -> np.ndarray:
    """(n, 4, 4) sensor -> odom poses at times t."""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    s, d, _ = plan.at(t)
    eps = 0.05
    s1, d1, _ = plan.at(t + eps)
    s0, d0, _ = plan.at(np.maximum(t - eps, 0.0))
    row = ref.sample(s)
    heading, kappa, grade, bank = row[:, 2], row[:, 3], row[:, 5], row[:, 6]
    ds = s1 - s0
    slip = np.where(ds > 1e-4, np.arctan2(d1 - d0, np.maximum(ds, 1e-4) * (1 - kappa * d)), 0.0)
    yaw = heading + slip
    pitch = -np.arctan(grade)
    roll = np.arctan(bank)
    rot = rotation_rpy(roll, pitch, yaw)
    base = ref.to_world(s, d)
    out = np.tile(np.eye(4), (t.size, 1, 1))
    out[:, :3, :3] = rot
    if mount.pitch or mount.roll:  # the sensor tilted on its mount, not the vehicle
        out[:, :3, :3] = rot @ rotation_rpy(np.array(mount.roll), np.array(mount.pitch),
                                            np.array(0.0))
    out[:, :3, 3] = base + rot @ np.array([mount.x, 0.0, mount.z])
    return out


def drifted(true_poses: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Odometry estimate with drift: relative motions get a scale error and translation and
    yaw noise, then are chained (level 1: ~1 % of distance, ~0.3 deg per 10 m)."""
    if level <= 0 or true_poses.shape[0] < 2:
        return true_poses.copy()
    scale = 1.0 + level * rng.normal(0.0, 0.01)
    out = np.empty_like(true_poses)
    out[0] = true_poses[0]
    for k in range(1, true_poses.shape[0]):
        rel = np.linalg.solve(true_poses[k - 1], true_poses[k])
        step = float(np.linalg.norm(rel[:3, 3]))
        rel[:3, 3] = rel[:3, 3] * scale + level * rng.normal(0.0, 0.003, 3) * (step + 0.01)
        dyaw = level * rng.normal(0.0, 5e-4 * step + 5e-5)
        c, s = np.cos(dyaw), np.sin(dyaw)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        rel[:3, :3] = rz @ rel[:3, :3]
        out[k] = out[k - 1] @ rel
    return out
