"""Public simulator API: a seeded road scene, LiDAR sweeps along the ego path, GT lane lines
and training samples (see samples.py) through the same decode + BEV path as the node.

    sim = Simulator(seed=3, sweeps=100, sensor='os1-64')
    for sweep in sim.sweeps():          # Sweep(stamp_ns, points, sensor_to_odom, ...)
        ...
    sim.scene.lane_lines                # GT: list of (K, 3) odom-frame polylines

Determinism: every component draws from its own generator spawned from the seed
(SeedSequence), and each sweep's noise from a generator keyed by (seed, sweep index), so a
sweep is the same whether it is generated alone or in sequence. The world is planned for
whole blocks of PLAN_BLOCK sweeps, so with the same seed and options a shorter run is the
start of a longer one (within a block).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from fhld_ros.sim import ego as ego_mod
from fhld_ros.sim.ground_grid import GroundGrid
from fhld_ros.sim.gt_lines import crop_to_disc
from fhld_ros.sim.layout import ROAD_CLASSES, TOPOLOGIES, Layout, TopologyEvent
from fhld_ros.sim.layout_builder import make_layout
from fhld_ros.sim.lidar import (
    DEFAULT_SENSOR,
    INTENSITY_SCALES,
    LAYOUTS,
    NO_RETURNS,
    SENSORS,
    Returns,
    SensorPreset,
    detect_and_measure,
    local_directions,
    pack_points,
)
from fhld_ros.sim.markings import NONE as NO_PAINT
from fhld_ros.sim.markings import Paint
from fhld_ros.sim.obstacles import (
    EGO,
    Boxes,
    Cylinders,
    Spheres,
    StaticObjects,
    Traffic,
    place_static,
    place_traffic,
    yaw_boxes,
)
from fhld_ros.sim.raycast import ObstacleCaster, RayBundle, cast_ground
from fhld_ros.sim.road import ReferenceLine, RoadShape, make_reference_line
from fhld_ros.sim.scene import PAINT, RoadLook, Surface

SPEED_RANGE = {'highway': (18.0, 30.0), 'urban': (5.0, 14.0), 'rural': (12.0, 25.0)}
PERIOD_S = 0.1  # 10 Hz sweeps
PLAN_BLOCK = 300  # sweeps: scenes are planned for whole blocks (see Simulator.__init__)
STAMP_BASE_NS = 1_700_000_000 * 1_000_000_000  # runs start at a plausible wall-clock time
GROUND_RANGE_M = 100.0  # ground beyond this is too grazing to return anything
MAX_SPEED = 30.0
MAX_SWEEPS = 6000  # 10 minutes of driving (road tables grow with the distance)
PAINT_RHO = {False: 0.55, True: 0.45}  # white / yellow paint, diffuse part
MAX_MOUNT_TILT_DEG = 5.0
PAINT_RETRO = 1.0  # glass-bead retro-reflection of fresh paint (relative)


@dataclass(frozen=True)
class SimConfig:
    """Options of a simulation (CLI flags map 1:1)."""

    sensor: str = DEFAULT_SENSOR
    columns: int | None = None  # horizontal resolution; default: the preset's
    layout: str | None = None  # 'ouster' | 'velodyne'; default: the preset's driver
    intensity: str | None = None  # 'reflectivity' | 'float' | 'u8'; default: the preset's
    no_return: str = 'zero'  # organised layout: no-return points all-zero or NaN
    road: str = 'auto'  # 'auto' | 'highway' | 'urban' | 'rural'
    topology: str | None = None  # force the first topology event (near the start)
    speed: float | None = None  # m/s; default: random for the road class
    odom_noise: float = 0.0  # odometry drift level (0 = exact, 1 = typical wheel odometry)
    motion_distortion: bool = False  # points in each column's own sensor frame (raw driver)
    noise: bool = True  # range / intensity noise and random dropouts
    # worn paint: None = the usual paint (fresh: ~6x the asphalt's diffuse reflectance, ~18x
    # its intensity with the glass beads); a number = beads worn off, the paint's reflectance
    # at most this many times the asphalt's
    paint_contrast: float | None = None
    markings: bool = True  # False: the same road with no paint at all (no lines, no GT)
    edge_lines: bool = True  # False: the same road without its edge lines (lanes to the curb)
    mount_z: float | None = None  # sensor height above the road; default: the preset's
    mount_pitch_deg: float = 0.0  # sensor tilted on its mount (+ pitch: looking down)
    mount_roll_deg: float = 0.0
    asphalt_rho: float | None = None  # scene.RoadLook: pavement brightness (KITTI-like ~0.25)
    gutter_ratio: float | None = None  # a strip along the paved edges, x the pavement
    seams: bool = False  # dark sealed cracks and joints
    # uncalibrated lasers: each laser's intensity gain log-normal with this sigma, drawn per
    # drive from its own stream (None: the preset's small spread, gain_sigma)
    laser_gain_sigma: float | None = None

    def validate(self) -> None:
        def bad(msg: str) -> None:
            raise ValueError(msg)
        if self.sensor not in SENSORS:
            bad(f'unknown sensor {self.sensor!r} (choose from {", ".join(SENSORS)})')
        if self.columns is not None and not 64 <= self.columns <= 4096:
            bad(f'columns must be in 64..4096, got {self.columns}')
        if self.layout is not None and self.layout not in LAYOUTS:
            bad(f'unknown layout {self.layout!r} (choose from {", ".join(LAYOUTS)})')
        if self.intensity is not None and self.intensity not in INTENSITY_SCALES:
            bad(f'unknown intensity scale {self.intensity!r} '
                f'(choose from {", ".join(INTENSITY_SCALES)})')
        if self.no_return not in NO_RETURNS:
            bad(f'no_return must be one of {", ".join(NO_RETURNS)}, got {self.no_return!r}')
        if self.road not in ('auto', *ROAD_CLASSES):
            bad(f'unknown road class {self.road!r} (choose from auto, {", ".join(ROAD_CLASSES)})')
        if self.topology is not None and self.topology not in TOPOLOGIES:
            bad(f'unknown topology {self.topology!r} (choose from {", ".join(TOPOLOGIES)})')
        if self.speed is not None and not 0.0 <= self.speed <= MAX_SPEED:
            bad(f'speed must be within 0..{MAX_SPEED:g} m/s, got {self.speed:g}')
        if not 0.0 <= self.odom_noise <= 10.0:
            bad(f'odom_noise must be within 0..10, got {self.odom_noise:g}')
        if self.paint_contrast is not None and not 1.0 <= self.paint_contrast <= 20.0:
            bad(f'paint_contrast must be within 1..20, got {self.paint_contrast:g}')
        if self.mount_z is not None and not 1.0 <= self.mount_z <= 3.0:
            bad(f'mount_z must be within 1..3 m, got {self.mount_z:g}')
        if max(abs(self.mount_pitch_deg), abs(self.mount_roll_deg)) > MAX_MOUNT_TILT_DEG:
            bad(f'mount pitch and roll must be within +-{MAX_MOUNT_TILT_DEG:g} degrees')
        if self.asphalt_rho is not None and not 0.02 <= self.asphalt_rho <= 0.6:
            bad(f'asphalt_rho must be within 0.02..0.6, got {self.asphalt_rho:g}')
        if self.gutter_ratio is not None and not 0.3 <= self.gutter_ratio <= 4.0:
            bad(f'gutter_ratio must be within 0.3..4, got {self.gutter_ratio:g}')
        if self.laser_gain_sigma is not None and not 0.0 <= self.laser_gain_sigma <= 1.0:
            bad(f'laser_gain_sigma must be within 0..1, got {self.laser_gain_sigma:g}')


@dataclass
class Sweep:
    """One simulated revolution, in the driver's layout."""

    index: int
    stamp_ns: int  # start of the revolution (column times are offsets from it)
    points: np.ndarray  # structured array (Ouster: height*width organised, row-major)
    height: int  # cloud height (beams for organised layouts, 1 otherwise)
    sensor_to_odom: np.ndarray  # (4, 4) true sensor pose at the stamp
    odom_pose: np.ndarray  # (4, 4) pose reported on /odom (with drift when enabled)
    labels: np.ndarray  # (N,) uint8 material per point (0: no return), aligned with points
    linear: np.ndarray = field(default_factory=lambda: np.zeros(3))  # velocity, sensor frame
    angular: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class Scene:
    """The static world and its ground truth."""

    road_class: str
    ref: ReferenceLine
    layout: Layout
    paint: Paint
    surface: Surface
    static: StaticObjects
    traffic: Traffic
    lane_lines: list[np.ndarray]  # GT (K, 3) odom-frame polylines, one per painted stripe

    @property
    def events(self) -> list[TopologyEvent]:
        return self.layout.events


def _ego_boxes(mount: ego_mod.Mount) -> Boxes:
    """The ego's body and cabin in the sensor frame (they hide the lowest beams)."""
    z = -mount.z
    xy = np.array([[-mount.x, 0.0], [-mount.x - 0.2, 0.0]])
    return yaw_boxes(xy, np.array([z + 0.2, z + 1.0]), np.array([z + 1.0, z + 1.5]),
                     np.zeros(2), np.array([4.7, 2.2]), np.array([1.9, 1.7]), EGO,
                     np.array([0.3, 0.3]))


def subset(prims: Boxes | Cylinders | Spheres, keep: np.ndarray):
    """The primitives where keep is true (same type)."""
    return type(prims)(*(getattr(prims, f)[keep] for f in prims.__dataclass_fields__))


class Simulator:
    """A seeded scene and a LiDAR driving through it for `sweeps` revolutions at 10 Hz."""

    def __init__(self, seed: int, sweeps: int = 100, sensor: str = DEFAULT_SENSOR,
                 **options: object) -> None:
        config = SimConfig(sensor=sensor, **options)  # type: ignore[arg-type]
        config.validate()
        if not 1 <= int(sweeps) <= MAX_SWEEPS:
            raise ValueError(f'sweeps must be in 1..{MAX_SWEEPS}, got {sweeps}')
        if int(seed) < 0:
            raise ValueError(f'seed must be >= 0, got {seed}')
        self.seed, self.n_sweeps, self.config = int(seed), int(sweeps), config
        self.preset: SensorPreset = SENSORS[config.sensor]
        self.columns = config.columns or self.preset.columns
        self.layout_name = config.layout or self.preset.layout
        self.scale = config.intensity or self.preset.intensity
        self.frame_id = 'lidar'
        rngs = [np.random.default_rng(c) for c in np.random.SeedSequence(self.seed).spawn(10)]
        r_class, r_road, r_layout, r_paint, r_surface, r_static, r_traffic, r_ego, r_odom, \
            r_lidar = rngs

        road_class = config.road
        if road_class == 'auto':
            road_class = ('highway' if config.topology in ('exit_ramp', 'entrance_ramp') else
                          str(r_class.choice(ROAD_CLASSES, p=(0.4, 0.4, 0.2))))
        if config.speed is not None:
            v0 = float(config.speed)
        elif road_class == 'urban' and r_class.random() < 0.05:
            v0 = 0.0  # waiting in traffic
        else:
            v0 = float(r_class.uniform(*SPEED_RANGE[road_class]))
        # the world is planned for whole blocks of sweeps, so runs of different lengths
        # within a block share one scene (a 50-sweep run is the start of a 100-sweep one)
        planned = -(-self.n_sweeps // PLAN_BLOCK) * PLAN_BLOCK
        duration = planned * PERIOD_S + 1.0
        travel = 1.15 * v0 * duration + 10.0
        shape = RoadShape(min_radius_m=300.0 if road_class == 'highway' else 50.0)
        crossfall = float(r_road.choice((-1.0, 1.0)) * r_road.uniform(0.01, 0.025))
        ref = make_reference_line(r_road, -200.0, travel + 500.0, shape, crossfall, 0.0)
        layout = make_layout(r_layout, r_paint, ref.s, road_class, 0.0, travel,
                             config.topology)
        if not config.edge_lines:  # many city streets paint no line along the curb
            layout = replace(layout, lines=[ln for ln in layout.lines if ln.kind != 'edge'])
        if not config.markings:  # drawn as usual, then stripped: the road stays the same
            layout = replace(layout, style=replace(layout.style, marked=False), lines=[])
        paint = Paint(ref, layout, r_paint, road_class)
        surface = Surface(ref, layout, r_surface, road_class,
                          RoadLook(config.asphalt_rho, config.gutter_ratio, config.seams))
        static = place_static(r_static, ref, layout, surface, road_class)
        self.plan = ego_mod.plan_ego(r_ego, layout, duration, v0)
        self.mount = ego_mod.Mount(z=config.mount_z or self.preset.mount_z,
                                   pitch=float(np.deg2rad(config.mount_pitch_deg)),
                                   roll=float(np.deg2rad(config.mount_roll_deg)))
        times = np.arange(planned) * PERIOD_S
        ego_s, ego_d, _ = self.plan.at(times)
        traffic = place_traffic(r_traffic, layout, ego_s, ego_d, times, v0, road_class)
        self.scene = Scene(road_class, ref, layout, paint, surface, static, traffic,
                           paint.polylines())
        true_poses = ego_mod.poses(ref, self.plan, times, self.mount)
        odom_poses = ego_mod.drifted(true_poses, r_odom, config.odom_noise)
        self.true_poses = true_poses[:self.n_sweeps]  # (n, 4, 4) sensor -> odom per sweep
        self.odom_poses = odom_poses[:self.n_sweeps]  # what /odom reports

        # sensor: beams sorted by elevation, per-beam gain, ego self-occlusion per ray
        elev = np.deg2rad(np.sort(np.asarray(self.preset.elevations_deg)))
        self.elevation = elev
        self.local_dirs, self.azimuth = local_directions(elev, self.columns)
        self.gains = np.clip(r_lidar.normal(1.0, self.preset.gain_sigma, elev.size), 0.6, 1.4)
        if config.laser_gain_sigma is not None:  # drawn after, so r_lidar's stream stays put
            r_gain = np.random.default_rng(np.random.SeedSequence([self.seed, 0x6A15]))
            self.gains = np.exp(r_gain.normal(0.0, config.laser_gain_sigma, elev.size))
        self_rays = RayBundle(np.zeros((self.columns, 3)), self.local_dirs, elev, self.azimuth,
                              0.0, 10.0)
        caster = ObstacleCaster(self_rays, tilt_margin=0.0)
        caster.boxes(_ego_boxes(self.mount))
        self._ego_t = caster.t
        self.grid = GroundGrid(surface)
        self._col_time = (np.arange(self.columns) + 0.5) / self.columns * PERIOD_S
        self._in_fov = np.abs(self.azimuth) <= np.deg2rad(self.preset.azimuth_fov_deg) / 2

    # -- sweeps -------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.n_sweeps

    def sweeps(self, start: int = 0, stop: int | None = None) -> Iterator[Sweep]:
        for k in range(start, self.n_sweeps if stop is None else min(stop, self.n_sweeps)):
            yield self.sweep(k)

    def _rays(self, k: int) -> RayBundle:
        t0 = k * PERIOD_S
        if self.config.motion_distortion:  # each column from its own pose
            pose = ego_mod.poses(self.scene.ref, self.plan, t0 + self._col_time, self.mount)
            dirs = np.einsum('wij,bwj->bwi', pose[:, :3, :3], self.local_dirs)
            origin = pose[:, :3, 3]
        else:
            pose = self.true_poses[k]
            rot = pose[:3, :3]  # elementwise: tiny BLAS matmuls are slow and thread-bound
            local = self.local_dirs
            dirs = np.stack([local[..., 0] * rot[i, 0] + local[..., 1] * rot[i, 1] +
                             local[..., 2] * rot[i, 2] for i in range(3)], axis=-1)
            origin = np.broadcast_to(pose[:3, 3], (self.columns, 3))
        centre = self.true_poses[k]
        yaw = float(np.arctan2(centre[1, 0], centre[0, 0]))
        return RayBundle(origin, dirs, self.elevation, self.azimuth, yaw, self.preset.max_range)

    def sweep(self, k: int) -> Sweep:
        """Sweep k (0-based), independent of which sweeps were generated before."""
        if not 0 <= k < self.n_sweeps:
            raise IndexError(f'sweep {k} out of range 0..{self.n_sweeps - 1}')
        scene, preset = self.scene, self.preset
        key = np.random.SeedSequence(self.seed, spawn_key=(1000, k))
        r_noise, r_struct = (np.random.default_rng(c) for c in key.spawn(2))
        rays = self._rays(k)
        nb, nw = rays.dirs.shape[:2]
        sensor_xy = self.true_poses[k, :2, 3]

        # obstacles first (static, traffic at mid-sweep): they bound the ground search
        caster = ObstacleCaster(rays, tilt_margin=np.deg2rad(7.0),
                                yaw_margin=0.02 + (0.08 if self.config.motion_distortion else 0))
        reach = preset.max_range + 20.0
        st = scene.static
        near = lambda c: np.hypot(*(c[:, :2] - sensor_xy).T) < reach  # noqa: E731
        caster.boxes(subset(st.boxes, near(st.boxes.centre)))
        caster.boxes(scene.traffic.boxes(scene.ref, scene.surface, (k + 0.5) * PERIOD_S,
                                         sensor_xy, reach))
        caster.cylinders(subset(st.cylinders, near(st.cylinders.base)))
        caster.spheres(subset(st.spheres, near(st.spheres.centre)), r_struct.random((nb, nw)))
        # ground; the ego's own body blocks rays but never returns
        blocked = np.minimum(caster.t, self._ego_t)
        ground_range = min(preset.max_range, GROUND_RANGE_M)
        self.grid.ensure(sensor_xy, ground_range + 5.0)
        origin = np.broadcast_to(rays.origin[None], (nb, nw, 3)).reshape(-1, 3)
        t_g, s_g, d_g = cast_ground(self.grid, scene.surface, origin, rays.dirs.reshape(-1, 3),
                                    np.minimum(blocked, ground_range).ravel())
        t_g = t_g.reshape(nb, nw)

        t = np.minimum(np.minimum(t_g, caster.t), self._ego_t)
        ground = np.isfinite(t_g) & (t_g <= t)
        obj = ~ground & (caster.t <= t) & np.isfinite(t)
        rho = np.zeros((nb, nw))
        retro = np.zeros((nb, nw))
        cos = np.ones((nb, nw))
        material = np.zeros((nb, nw), dtype=np.uint8)
        if caster.material:
            ids = caster.obj[obj]
            rho[obj] = np.asarray(caster.rho)[ids]
            material[obj] = np.asarray(caster.material, dtype=np.uint8)[ids]
            cos[obj] = caster.cos[obj]
        gi = np.flatnonzero(ground.ravel())
        if gi.size:
            dirs_g = rays.dirs.reshape(-1, 3)[gi]
            z_g = origin[gi, 2] + t_g.ravel()[gi] * dirs_g[:, 2]
            g_mat, g_rho, g_retro, g_cos = self._shade_ground(s_g[gi], d_g[gi], z_g, dirs_g)
            for arr, val in ((material, g_mat), (rho, g_rho), (retro, g_retro), (cos, g_cos)):
                arr.reshape(-1)[gi] = val
        t_hit = np.where((ground | obj) & self._in_fov, t, np.inf)
        valid, r_meas, value = detect_and_measure(
            Returns(rho, retro, cos, t_hit), preset, self.scale, self.gains,
            r_noise if self.config.noise else None)
        xyz = (r_meas[..., None] * self.local_dirs).astype(np.float32)
        points, height, order = pack_points(self.layout_name, self.scale, self.config.no_return,
                                            xyz, valid, value, r_meas, self._col_time)
        labels = np.where(valid, material, 0).ravel()[order]
        stamp = STAMP_BASE_NS + int(round(k * PERIOD_S * 1e9))
        return Sweep(k, stamp, points, height, self.true_poses[k], self.odom_poses[k],
                     labels.astype(np.uint8), *self._velocity(k))

    def _shade_ground(self, s: np.ndarray, d: np.ndarray, z: np.ndarray, dirs: np.ndarray
                      ) -> tuple[np.ndarray, ...]:
        """Material, diffuse reflectance, retro strength and |cos incidence| of ground hits."""
        scene = self.scene
        rows = scene.surface.rows(s)
        material, rho = scene.surface.material(s, d, rows)
        kind, contrast, line = scene.paint.lookup(s, d)
        paint = kind != NO_PAINT
        retro = np.zeros(s.shape)
        if paint.any():
            yellow = np.zeros(s.shape, dtype=bool)
            on_line = line >= 0
            yellow[on_line] = scene.paint.yellow[line[on_line]]
            c = contrast[paint]
            worn = self.config.paint_contrast
            if worn is None:
                rho[paint] = rho[paint] * (1.0 - c) + np.where(
                    yellow[paint], PAINT_RHO[True], PAINT_RHO[False]) * c
                retro[paint] = PAINT_RETRO * c
            else:  # beads gone: no retro-reflection, reflectance relative to the asphalt
                rho[paint] = rho[paint] * (1.0 + (worn - 1.0) * c)
            material[paint] = PAINT
        dzs, dzd = scene.surface.normal_slopes(s, d, z, rows=rows)
        heading = np.interp(s, scene.ref.s, scene.ref.column('heading'))
        ch, sh = np.cos(heading), np.sin(heading)
        gx, gy = dzs * ch - dzd * sh, dzs * sh + dzd * ch
        cos = np.abs(-gx * dirs[:, 0] - gy * dirs[:, 1] + dirs[:, 2]) / np.sqrt(
            1.0 + gx * gx + gy * gy)
        return material, rho, retro, cos

    def _velocity(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame linear and angular velocity at sweep k (finite differences)."""
        t = k * PERIOD_S
        a, b = ego_mod.poses(self.scene.ref, self.plan, np.array([t, t + 0.05]), self.mount)
        rel = np.linalg.solve(a, b)
        angle = np.arctan2(rel[1, 0], rel[0, 0])
        return rel[:3, 3] / 0.05, np.array([0.0, 0.0, angle / 0.05])

    # -- ground truth helpers --------------------------------------------------------------
    def lane_lines_near(self, xy: np.ndarray, radius: float) -> tuple[list[np.ndarray],
                                                                        list[int]]:
        """GT polylines cropped to a disc around xy (pieces split where they leave it)."""
        return crop_to_disc(self.scene.lane_lines, np.asarray(xy, dtype=np.float64), radius)
