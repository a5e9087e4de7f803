"""A pinhole front camera rendered from the simulator's scene (`fhld simulate --camera`).

One ray per pixel through the same ground heightfield and obstacle primitives as the LiDAR
(raycast.py), at the sweep's stamp and the LiDAR's true pose composed with the camera's mount.
Shading is simple and fixed: albedo by material (asphalt with its patches and a fine grain,
white and yellow paint by its contrast, concrete, gravel, grass), a sun plus sky light on
normals (analytic on the ground, from the hit points' screen-space derivatives on obstacles),
windows on buildings, a sky gradient, and haze that hides the end of the rendered ground.

Camera optical frame: x right, y down, z forward. `T_cloud_camera` is the camera's pose in the
LiDAR (cloud) frame; pixel (0, 0)'s centre is at u = v = 0 (OpenCV).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.sim.ground_grid import GroundGrid
from fhld_ros.sim.markings import LINE
from fhld_ros.sim.markings import NONE as NO_PAINT
from fhld_ros.sim.obstacles import (
    BARRIER,
    BUILDING,
    VEGETATION,
    VEHICLE,
    Spheres,
)
from fhld_ros.sim.pinhole_caster import PinholeCaster, screen_normals
from fhld_ros.sim.raycast import ObstacleCaster, RayBundle, cast_ground
from fhld_ros.sim.scene import ASPHALT, CONCRETE, GRASS, GRAVEL
from fhld_ros.sim.simulator import PERIOD_S, STAMP_BASE_NS, Simulator, subset

CAMERA_FRAME = 'camera'
DEFAULT_SIZE = (960, 600)  # width, height (px)
HFOV_DEG = 70.0  # horizontal field of view; square pixels (fx = fy)
MOUNT_FORWARD_M = 1.2  # camera ahead of the LiDAR ...
MOUNT_DOWN_M = 0.3  # ... and below it (behind the windscreen)
PITCH_DEG = 3.0  # optical axis below the LiDAR's horizontal
RENDER_RANGE_M = 150.0  # ground and obstacles beyond fade into the haze
HAZE_M = 400.0  # distance of 1/e haze transmission
PAINT_AA_M = 25.0  # beyond this range paint is averaged over the pixel's footprint

SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])  # world, unit
AMBIENT, SUN_GAIN = 0.55, 0.65
EXPOSURE = 1.25
# linear albedos
ASPHALT_TINT = np.array([1.0, 1.0, 1.05])
WHITE_PAINT = np.array([0.72, 0.72, 0.70])
# yellow paint runs from orange (US thermoplastic) to lemon (Chinese and European roads): each
# road its own, so a network does not learn one hue of yellow as "the" centre line
YELLOW_PAINTS = np.array([[0.70, 0.48, 0.06], [0.70, 0.66, 0.20]])
# other ground: (albedo, the material's nominal rho in scene.Surface.material: it scales it)
GROUND_ALBEDO = {CONCRETE: (np.array([0.36, 0.35, 0.33]), 0.30),
                 GRAVEL: (np.array([0.30, 0.27, 0.22]), 0.22),
                 GRASS: (np.array([0.10, 0.19, 0.05]), 0.35)}
CAR_PAINTS = np.array([[0.75, 0.75, 0.75], [0.45, 0.46, 0.48], [0.03, 0.03, 0.035],
                       [0.12, 0.12, 0.13], [0.45, 0.04, 0.03], [0.04, 0.10, 0.35],
                       [0.05, 0.15, 0.08], [0.50, 0.42, 0.30]])
FACADES = np.array([[0.45, 0.40, 0.33], [0.38, 0.20, 0.14], [0.40, 0.40, 0.40],
                    [0.55, 0.52, 0.45], [0.30, 0.32, 0.36]])
WINDOW = np.array([0.05, 0.07, 0.09])
FOLIAGE = np.array([0.07, 0.15, 0.04])
BARK = np.array([0.14, 0.10, 0.06])
METAL = np.array([0.30, 0.31, 0.33])
BARRIER_ALBEDO = np.array([0.40, 0.40, 0.38])
SKY_HORIZON = np.array([0.80, 0.86, 0.93])  # display (sRGB 0-1) values
SKY_ZENITH = np.array([0.33, 0.52, 0.84])
HAZE = SKY_HORIZON ** 2.2  # linear


def sweep_stamp_ns(k: int) -> int:
    """The stamp of sweep k (Simulator.sweep's clock): the camera exposes at it."""
    return STAMP_BASE_NS + int(round(k * PERIOD_S * 1e9))


def intrinsics(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    """3x3 K of a centred pinhole with square pixels."""
    f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)],
                     [0.0, 0.0, 1.0]])


def mount_extrinsic(forward: float = MOUNT_FORWARD_M, down: float = MOUNT_DOWN_M,
                    pitch_deg: float = PITCH_DEG) -> np.ndarray:
    """T_cloud_camera: the optical frame (x right, y down, z forward, pitched down) in the
    LiDAR frame (x forward, y left, z up)."""
    p = np.deg2rad(pitch_deg)
    T = np.eye(4)
    # columns: the camera's x, y, z axes in LiDAR coordinates
    T[:3, :3] = np.array([[0.0, -np.sin(p), np.cos(p)],
                          [-1.0, 0.0, 0.0],
                          [0.0, -np.cos(p), -np.sin(p)]])
    T[:3, 3] = (forward, 0.0, -down)
    return T


@dataclass
class CameraImage:
    """One rendered image: colours, depth along the optical axis (inf: nothing within
    RENDER_RANGE_M) and the camera's true pose."""

    index: int  # sweep index
    stamp_ns: int
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 camera z (m)
    camera_to_odom: np.ndarray  # (4, 4)


class SimCamera:
    """A front camera on the simulator's ego: `render(k)` gives the image at sweep k."""

    def __init__(self, sim: Simulator, width: int = DEFAULT_SIZE[0],
                 height: int = DEFAULT_SIZE[1], hfov_deg: float = HFOV_DEG,
                 T_cloud_camera: np.ndarray | None = None, K: np.ndarray | None = None) -> None:
        if not (16 <= width <= 8192 and 16 <= height <= 8192):
            raise ValueError(f'camera size must be within 16..8192 px, got {width}x{height}')
        self.sim, self.width, self.height = sim, int(width), int(height)
        self.K = intrinsics(self.width, self.height, hfov_deg) if K is None else \
            np.array(K, dtype=np.float64)  # K given: hfov_deg is not used
        self.D = np.zeros(5)
        self.T_cloud_camera = mount_extrinsic() if T_cloud_camera is None else \
            np.asarray(T_cloud_camera, dtype=np.float64)
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64),
                           np.arange(self.height, dtype=np.float64))
        rays = np.stack([(u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1],
                         np.ones_like(u)], axis=-1)
        norm = np.linalg.norm(rays, axis=-1)
        self._rays_cam = rays / norm[..., None]  # unit directions in the optical frame
        self._depth_per_t = (1.0 / norm).astype(np.float32)  # camera z per metre of ray
        # a grid of its own: sharing the LiDAR's would shift its float32 origin and so its
        # ranges in the last bits, and sweeps must not depend on whether a camera renders
        self.grid = GroundGrid(sim.scene.surface)
        share = np.random.default_rng(np.random.SeedSequence([sim.seed, 0x7E11])).random()
        self.yellow_paint = YELLOW_PAINTS[0] + share * (YELLOW_PAINTS[1] - YELLOW_PAINTS[0])

    def calibration(self) -> CameraCalibration:
        return CameraCalibration(self.width, self.height, self.K.copy(), self.D.copy(),
                                 np.linalg.inv(self.T_cloud_camera), CAMERA_FRAME,
                                 self.sim.frame_id)

    def pose(self, k: int) -> np.ndarray:
        """Camera -> odom at sweep k (the LiDAR's true pose composed with the mount)."""
        return self.sim.true_poses[k] @ self.T_cloud_camera

    # -- rendering -----------------------------------------------------------------------
    def render(self, k: int) -> CameraImage:
        if not 0 <= k < self.sim.n_sweeps:
            raise IndexError(f'sweep {k} out of range 0..{self.sim.n_sweeps - 1}')
        pose = self.pose(k)
        origin, dirs = pose[:3, 3], self.world_dirs(pose)
        caster, kinds = self.cast_obstacles(k, origin, dirs)
        t_g, s_g, d_g = self._cast_ground(origin, dirs, caster.t)
        ground = np.isfinite(t_g) & (t_g <= caster.t)
        obj = ~ground & np.isfinite(caster.t)
        _fill_curb_gaps(ground, obj, dirs, (t_g, s_g, d_g))
        t = np.where(ground, t_g, caster.t)

        gi, oi = np.flatnonzero(ground), np.flatnonzero(obj)
        flat_dirs = dirs.reshape(-1, 3)
        colour = np.empty((gi.size + oi.size, 3), dtype=np.float32)
        if gi.size:
            z = origin[2] + t_g.ravel()[gi] * flat_dirs[gi, 2]
            colour[:gi.size] = self._shade_ground(s_g.ravel()[gi], d_g.ravel()[gi], z,
                                                  t_g.ravel()[gi], origin[2] - z)
        if oi.size:
            colour[gi.size:] = self._shade_obstacles(caster, kinds, origin, dirs, t, obj, oi)
        hit = np.concatenate([gi, oi])
        depth = np.full(t.size, np.inf, dtype=np.float32)
        depth[hit] = t.ravel()[hit]
        rgb = self._finish(colour, flat_dirs, depth, hit)
        depth *= self._depth_per_t.ravel()
        return CameraImage(k, sweep_stamp_ns(k), rgb, depth.reshape(t.shape), pose)

    def world_dirs(self, pose: np.ndarray) -> np.ndarray:
        """(H, W, 3) unit ray directions of the pixels in the odom frame, camera pose `pose`."""
        rot, local = pose[:3, :3], self._rays_cam
        return np.stack([local[..., 0] * rot[i, 0] + local[..., 1] * rot[i, 1] +
                         local[..., 2] * rot[i, 2] for i in range(3)], axis=-1)

    def cast_obstacles(self, k: int, origin: np.ndarray, dirs: np.ndarray, cull: bool = True
                       ) -> tuple[ObstacleCaster, np.ndarray]:
        """Nearest obstacle per pixel, and the primitive kind (0 box, 1 cylinder, 2 sphere) of
        each object id the caster recorded. cull=False: every pixel against every object."""
        scene = self.sim.scene
        # elevation along rows and azimuth along columns vary smoothly: every 4th pixel (and
        # the last) is enough for the culling bounds, pinhole_caster.ANGLE_MARGIN covers the rest
        cols = np.unique(np.append(np.arange(0, self.width, 4), self.width - 1))
        rows = np.unique(np.append(np.arange(0, self.height, 4), self.height - 1))
        el = np.arcsin(np.clip(dirs[:, cols, 2], -1.0, 1.0))
        centre = dirs[self.height // 2, self.width // 2]
        yaw = float(np.arctan2(centre[1], centre[0]))
        sub = dirs[rows]
        az = (np.arctan2(sub[..., 1], sub[..., 0]) - yaw + np.pi) % (2 * np.pi) - np.pi
        rays = RayBundle(np.broadcast_to(origin, (self.width, 3)), dirs, el[:, 0], az[0], yaw,
                         RENDER_RANGE_M)
        caster = PinholeCaster(rays, el, az, cull)
        reach = RENDER_RANGE_M + 20.0
        xy = origin[:2]
        near = lambda c: np.hypot(*(c[:, :2] - xy).T) < reach  # noqa: E731
        st = scene.static
        caster.boxes(subset(st.boxes, near(st.boxes.centre)))
        caster.boxes(scene.traffic.boxes(scene.ref, scene.surface, k * PERIOD_S, xy, reach))
        n_boxes = len(caster.material)
        caster.cylinders(subset(st.cylinders, near(st.cylinders.base)))
        n_cylinders = len(caster.material)
        # crowns: denser than the LiDAR's porosity, gaps in small blocks of pixels (leaves)
        crowns = subset(st.spheres, near(st.spheres.centre))
        crowns = Spheres(crowns.centre, crowns.radius, crowns.material, crowns.rho,
                         0.25 * crowns.porosity)
        rng = np.random.default_rng(np.random.SeedSequence(self.sim.seed, spawn_key=(2000, k)))
        leaves = rng.random((self.height // 3 + 1, self.width // 3 + 1))
        caster.spheres(crowns, np.repeat(np.repeat(leaves, 3, 0), 3, 1)[:self.height,
                                                                         :self.width])
        kinds = np.zeros(len(caster.material), dtype=np.int8)
        kinds[n_boxes:n_cylinders], kinds[n_cylinders:] = 1, 2
        return caster, kinds

    def _cast_ground(self, origin: np.ndarray, dirs: np.ndarray, blocked: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        reach = RENDER_RANGE_M + 5.0
        self.grid.ensure(origin[:2], reach, self._seen_tiles(origin, dirs, reach))
        flat = dirs.reshape(-1, 3)
        t, s, d = cast_ground(self.grid, self.sim.scene.surface,
                              np.broadcast_to(origin, flat.shape), flat,
                              np.minimum(blocked, RENDER_RANGE_M).ravel())
        shape = dirs.shape[:2]
        return t.reshape(shape), s.reshape(shape), d.reshape(shape)

    def _seen_tiles(self, origin: np.ndarray, dirs: np.ndarray, reach: float
                    ) -> set[tuple[int, int]] | None:
        """The ground tiles under the sector of azimuths the rays span (None: the whole
        square, for rays close to vertical, whose azimuth says little)."""
        rays = np.concatenate([dirs[::4, ::4].reshape(-1, 3), dirs[-1], dirs[:, -1]])
        if np.hypot(rays[:, 0], rays[:, 1]).min() < 0.2:
            return None
        centre = dirs[self.height // 2, self.width // 2]
        yaw = float(np.arctan2(centre[1], centre[0]))
        az = (np.arctan2(rays[:, 1], rays[:, 0]) - yaw + np.pi) % (2 * np.pi) - np.pi
        return self.grid.tiles_in_sector(origin, (yaw + az.min(), yaw + az.max()), reach)

    # -- shading (linear RGB, lit) ------------------------------------------------------
    def _shade_ground(self, s: np.ndarray, d: np.ndarray, z: np.ndarray, t: np.ndarray,
                      drop: np.ndarray) -> np.ndarray:
        """Lit colours of ground hits at road coordinates (s, d), height z, range t, drop below
        the camera."""
        scene, worn = self.sim.scene, self.sim.config.paint_contrast
        rows = scene.surface.rows(s)
        material, rho = scene.surface.material(s, d, rows)
        # visible asphalt ~0.1-0.25; its patches (rho +-25 %) a little softer than in the NIR
        base = scene.surface.asphalt
        albedo = ((base + 0.6 * (rho - base)) * 1.6)[:, None] * ASPHALT_TINT
        for mat, (colour, nominal) in GROUND_ALBEDO.items():
            sel = material == mat
            albedo[sel] = colour * (rho[sel] / nominal)[:, None]
        grain = _hash01(np.floor(s / 0.04), np.floor(d / 0.04))
        albedo *= (0.94 + 0.12 * grain)[:, None]
        paved = np.flatnonzero(material == ASPHALT)  # paint lies on the pavement only
        kind, contrast, line = self._paint(s[paved], d[paved], t[paved], drop[paved])
        painted = kind != NO_PAINT
        paint = paved[painted]
        if paint.size:
            kind, contrast, line = kind[painted], contrast[painted], line[painted]
            yellow = np.zeros(paint.size, dtype=bool)
            on_line = (kind == LINE) & (line >= 0)
            yellow[on_line] = scene.paint.yellow[line[on_line]]
            target = np.where(yellow[:, None], self.yellow_paint, WHITE_PAINT)
            if worn is not None:  # beads and pigment gone: only `worn` times the asphalt
                grey = albedo[paint].mean(axis=1, keepdims=True)
                target = target / target.mean(axis=1, keepdims=True) * grey * worn
            c = contrast[:, None].astype(np.float64)
            albedo[paint] = albedo[paint] * (1.0 - c) + target * c * (
                0.96 + 0.08 * grain[paint, None])
        dzs, dzd = scene.surface.normal_slopes(s, d, z, rows=rows)
        heading = np.interp(s, scene.ref.s, scene.ref.column('heading'))
        ch, sh = np.cos(heading), np.sin(heading)
        gx, gy = dzs * ch - dzd * sh, dzs * sh + dzd * ch
        sun = np.maximum(-gx * SUN[0] - gy * SUN[1] + SUN[2], 0.0) / np.sqrt(1 + gx * gx + gy * gy)
        return albedo * (AMBIENT + SUN_GAIN * sun)[:, None]

    def _paint(self, s: np.ndarray, d: np.ndarray, t: np.ndarray, drop: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Paint.lookup at the pixels' ground points; from PAINT_AA_M on, where a pixel is about
        as wide as a stripe, the mean contrast of 4 samples over its footprint (a thin far line
        turns grey instead of breaking into dots)."""
        paint = self.sim.scene.paint
        kind, contrast, line = paint.lookup(s, d)
        far = np.flatnonzero(t > PAINT_AA_M)
        if far.size == 0:
            return kind, contrast, line
        across = 0.25 * t[far] / self.K[0, 0]
        along = 0.25 * t[far] ** 2 / (self.K[1, 1] * np.maximum(drop[far], 0.5))
        total = np.zeros(far.size, dtype=np.float32)
        for a, b in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            k2, c2, l2 = paint.lookup(s[far] + a * along, d[far] + b * across)
            total += c2
            new = (kind[far] == NO_PAINT) & (k2 != NO_PAINT)  # its kind and line, for colour
            kind[far[new]], line[far[new]] = k2[new], l2[new]
        contrast[far] = 0.25 * total
        kind[far[total == 0]] = NO_PAINT
        return kind, contrast, line

    def _shade_obstacles(self, caster: ObstacleCaster, kinds: np.ndarray, origin: np.ndarray,
                         dirs: np.ndarray, t: np.ndarray, obj: np.ndarray, oi: np.ndarray
                         ) -> np.ndarray:
        """Colours of the obstacle pixels oi (flat indices of the mask obj)."""
        ids = caster.obj.ravel()[oi]
        material = np.asarray(caster.material, dtype=np.uint8)[ids]
        rho = np.asarray(caster.rho)[ids]
        kind = kinds[ids]
        pick = np.floor(rho * 997.0).astype(int)  # a stable per-object choice from its rho
        albedo = np.empty((ids.size, 3))
        albedo[:] = METAL
        albedo[material == BARRIER] = BARRIER_ALBEDO
        albedo[(material == VEGETATION) & (kind == 2)] = FOLIAGE
        albedo[(material == VEGETATION) & (kind != 2)] = BARK
        car = material == VEHICLE
        albedo[car] = CAR_PAINTS[pick[car] % len(CAR_PAINTS)]
        points = origin + t.ravel()[oi, None] * dirs.reshape(-1, 3)[oi]
        house = material == BUILDING
        if house.any():
            facade = FACADES[pick[house] % len(FACADES)]
            p = points[house]
            storey = np.mod(p[:, 2], 3.2) / 3.2  # windows: a grid on every face
            bay = np.mod(p[:, 0] + p[:, 1], 2.6) / 2.6
            window = (storey > 0.35) & (storey < 0.8) & (bay > 0.2) & (bay < 0.7)
            albedo[house] = np.where(window[:, None], WINDOW, facade)
        normal = screen_normals(origin, dirs, t, obj)
        sun = np.maximum(normal @ SUN, 0.0)
        view = 0.55 + 0.45 * caster.cos.ravel()[oi]
        return albedo * (AMBIENT * view + SUN_GAIN * sun)[:, None]

    def _finish(self, colour: np.ndarray, dirs: np.ndarray, depth: np.ndarray,
                hit: np.ndarray) -> np.ndarray:
        """Haze, exposure and gamma (a table) on the hit pixels (flat indices), the sky on the
        others."""
        rgb = np.empty((depth.size, 3), dtype=np.uint8)
        t = depth[hit]
        edge = np.clip((t - 0.75 * RENDER_RANGE_M) / (0.25 * RENDER_RANGE_M), 0.0, 1.0)
        fog = np.maximum(1.0 - np.exp(-t / np.float32(HAZE_M)), edge * edge * (3 - 2 * edge))
        lit = colour * (np.float32(EXPOSURE) * (1 - fog))[:, None]
        lit += HAZE.astype(np.float32) * fog[:, None]
        lit *= _GAMMA.size - 1
        np.clip(lit, 0, _GAMMA.size - 1, out=lit)
        rgb[hit] = np.take(_GAMMA, lit.astype(np.uint16))
        sky = np.ones(depth.size, dtype=bool)
        sky[hit] = False
        up = np.clip(dirs[sky, 2] / 0.45, 0.0, 1.0) ** 0.6
        rgb[sky] = np.round(255 * (SKY_HORIZON + (SKY_ZENITH - SKY_HORIZON) * up[:, None]))
        return rgb.reshape(self.height, self.width, 3)


def _fill_curb_gaps(ground: np.ndarray, obj: np.ndarray, dirs: np.ndarray,
                    fields: tuple[np.ndarray, ...], max_gap: int = 60) -> None:
    """Downward pixels that missed between ground pixels at most max_gap rows above and below
    (or the image's bottom) take the values of the nearer of the two (in place). The ground
    search rejects some roots at curbs, where the height steps and the cached heightfield
    smooths the step."""
    miss = ~ground & ~obj & (dirs[..., 2] < 0)
    if not miss.any():
        return
    h = ground.shape[0]
    rows = np.arange(h)[:, None]
    above = np.maximum.accumulate(np.where(ground, rows, -h), axis=0)
    # the image's bottom edge counts as ground below (a gap may run out of the image)
    below = np.minimum.accumulate(np.where(ground, rows, h)[::-1], axis=0)[::-1]
    fill = miss & (rows - above <= max_gap) & (below - rows <= max_gap)
    if not fill.any():
        return
    r, c = np.nonzero(fill)
    up, down = above[r, c], below[r, c]
    src = np.where((r - up < down - r) | (down == h), up, down)
    for field in fields:
        field[r, c] = field[src, c]
    ground[r, c] = True


_GAMMA = np.round(255.0 * np.linspace(0.0, 1.0, 4096) ** (1 / 2.2)).astype(np.uint8)


def _hash01(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random value in [0, 1) per integer cell (a, b)."""
    x = np.sin(np.mod(a, 10007.0) * 12.9898 + np.mod(b, 10007.0) * 78.233) * 43758.5453
    return x - np.floor(x)
