"""Simulated drives as SALAD samples: the simulator's front camera (sim/camera.py) with, per
seed, its own mount height, pitch, field of view and principal point, and as lanes the 3D GT of
exactly what the image shows (sim/labels2d_gt.py: cut at the image border, at LABEL_RANGE_M and
where the rendered depth hides them), in the camera's optical frame.

Seeds: SALAD's training and held-out test drives use their own ranges (salad_seeds), apart
from each other and from the LiDAR detector's (training below data.cache.TEST_SEED_BASE, its
test set from there, `fhld autolabel-eval` from TEST_SEED_BASE + 500 000). A seed's scene
(sensor preset, so the LiDAR mount the camera hangs from, and topology event) follows
data.cache.scenario_for_seed, its road class and speed the simulator's own draw.
"""
from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from fhld_ros.data.cache import scenario_for_seed
from fhld_ros.data.variation import road_variation
from fhld_ros.errors import ConfigError
from fhld_ros.salad.config import HEIGHT_RANGE_M
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.sim.camera import (
    HFOV_DEG,
    MOUNT_FORWARD_M,
    PITCH_DEG,
    CameraImage,
    SimCamera,
    intrinsics,
)
from fhld_ros.sim.camera import mount_extrinsic as camera_mount
from fhld_ros.sim.labels2d_gt import sim_image_labels
from fhld_ros.sim.simulator import MAX_SWEEPS, Simulator

SALAD_TRAIN_SEED_BASE = 3_000_000
SALAD_TEST_SEED_BASE = 4_000_000
SALAD_VALIDATION_SEED_BASE = 5_000_000  # for choosing settings, so the test seeds stay unseen
SALAD_SEED_SPAN = 1_000_000  # seeds per split: [base, base + span)
SPLITS = {'train': SALAD_TRAIN_SEED_BASE, 'test': SALAD_TEST_SEED_BASE,
          'val': SALAD_VALIDATION_SEED_BASE}
DEFAULT_SIZE = (960, 540)  # width, height (px)
FRAME_STRIDE = 10  # sweeps between a drive's frames (1 s at 10 Hz)
# the camera drawn per seed (randomise=True)
PITCH_RANGE_DEG = (-1.0, 5.0)  # optical axis below the horizontal (+: looking down)
HFOV_RANGE_DEG = (50.0, 90.0)
PRINCIPAL_JITTER = 0.03  # principal point off the image centre, up to this share of the size
FIXED_HEIGHT_M = 1.5  # randomise=False: this height, PITCH_DEG and HFOV_DEG, centred
MAX_SIDE_M = 3.0  # --camera-side: a lane's width


@dataclass(frozen=True)
class CameraDraw:
    """The camera of one seed: height above the road (m), pitch (deg, + down), horizontal FOV
    (deg), principal point offset from the image centre (fractions of width and height), and
    how far left (+) of the car's centre line it sits (m)."""

    height_m: float
    pitch_deg: float
    hfov_deg: float
    principal_offset: tuple[float, float] = (0.0, 0.0)
    left_m: float = 0.0

    def intrinsics(self, size: tuple[int, int]) -> np.ndarray:
        """K of a (width, height) image: square pixels, the principal point shifted."""
        width, height = size
        K = intrinsics(width, height, self.hfov_deg)
        K[0, 2] += self.principal_offset[0] * width
        K[1, 2] += self.principal_offset[1] * height
        return K

    def extrinsic(self, lidar_height_m: float) -> np.ndarray:
        """T_cloud_camera on a LiDAR lidar_height_m above the road."""
        T = camera_mount(MOUNT_FORWARD_M, lidar_height_m - self.height_m, self.pitch_deg)
        T[1, 3] = self.left_m
        return T


def check_heights(heights_m: tuple[float, float]) -> tuple[float, float]:
    """A camera height range (low, high) in metres, checked."""
    low, high = map(float, heights_m)
    if not 0 < low <= high:
        raise ValueError(f'camera heights must be 0 < low <= high metres above the road, got '
                         f'{low:g}..{high:g}')
    return low, high


@dataclass(frozen=True)
class DriveVariant:
    """How a run's simulated drives differ from their seeds' own.

    Where the cameras sit: heights_m, their height range over the road (None: each seed its own
    within HEIGHT_RANGE_M); side_m, up to this far left or right of the car's centre line (0: on
    it). The cars drive their lanes' centres, so with side_m 0 no line ever runs right under the
    camera, straight up the image, as one does under a car that straddles it or a camera
    mounted off centre.

    How the roads look: with road_look each seed draws data.variation.road_variation: half the
    roads paint no line along their kerbs (the lanes run to the kerb), and some have gutters
    along the paved edges, sealed seams or bright pavement. Without it every road paints a line
    just inside each kerb, and a network learns "kerb => lane line".
    """

    heights_m: tuple[float, float] | None = None
    side_m: float = 0.0
    road_look: bool = False

    def __post_init__(self) -> None:
        if self.heights_m is not None:
            object.__setattr__(self, 'heights_m', check_heights(self.heights_m))
        if not 0.0 <= self.side_m <= MAX_SIDE_M:
            raise ValueError(f'the cameras\' side offset must be within 0..{MAX_SIDE_M:g} m, '
                             f'got {self.side_m:g}')

    def tag(self) -> str:
        """What sets this variant apart from the seeds' own, for file names ('' for none)."""
        heights = '' if self.heights_m is None else \
            f'_h{self.heights_m[0]:.2f}-{self.heights_m[1]:.2f}'
        return (heights + (f'_s{self.side_m:.2f}' if self.side_m else '') +
                ('_look' if self.road_look else ''))

    def meta(self) -> dict[str, Any]:
        """What trained weights record of it."""
        return {**({'camera_heights_m': list(self.heights_m)} if self.heights_m else {}),
                **({'camera_side_m': self.side_m} if self.side_m else {}),
                **({'road_look': True} if self.road_look else {})}

    def road(self, seed: int) -> dict[str, Any]:
        """The simulator options of the seed's road (none: its own)."""
        return road_variation(seed) if self.road_look else {}


SEEDS_OWN = DriveVariant()


def add_variant_arguments(parser: argparse.ArgumentParser) -> None:
    """--camera-height M [HIGH], --camera-side M and --road-look, for the commands that render
    drives."""
    parser.add_argument('--camera-height', type=float, nargs='+', metavar='M',
                        help='the simulated cameras at M metres over the road, or drawn within '
                        f'M..HIGH (default: each seed its own, {HEIGHT_RANGE_M[0]:g}-'
                        f'{HEIGHT_RANGE_M[1]:g} m), each keeping its pitch and lens')
    parser.add_argument('--camera-side', type=float, default=0.0, metavar='M',
                        help='the simulated cameras drawn up to M metres left or right of the '
                        'car\'s centre line (default 0: on it), so lines pass under them')
    parser.add_argument('--road-look', action='store_true',
                        help='the roads drawn as the LiDAR detector\'s training draws them: '
                        'half without lines along their kerbs, some with gutters, sealed seams '
                        'or bright pavement (default: each road as its seed draws it)')


def drive_variant(args: argparse.Namespace) -> DriveVariant:
    """--camera-height, --camera-side and --road-look, checked."""
    heights = args.camera_height
    if heights is not None and len(heights) > 2:
        raise ConfigError(f'--camera-height takes M or LOW HIGH, got {heights}')
    try:
        return DriveVariant(None if heights is None else (heights[0], heights[-1]),
                            args.camera_side, args.road_look)
    except ValueError as exc:
        raise ConfigError(f'--camera-height / --camera-side: {exc}') from None


def camera_for_seed(seed: int, randomise: bool = True, variant: DriveVariant = SEEDS_OWN
                    ) -> CameraDraw:
    """The seed's camera, from its own generator (the scene's draws stay what they are);
    variant: its height from variant.heights_m instead of HEIGHT_RANGE_M, at the same place in
    it (a user's mount, e.g. a truck's 2.6 m; (M, M): every camera at M), and its side offset,
    the rest unchanged."""
    if not randomise:
        return CameraDraw(FIXED_HEIGHT_M, PITCH_DEG, HFOV_DEG)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5A1AD]))
    share, pitch, hfov = (float(rng.uniform(*r)) for r in
                          ((0.0, 1.0), PITCH_RANGE_DEG, HFOV_RANGE_DEG))
    low, high = variant.heights_m or HEIGHT_RANGE_M
    du, dv = rng.uniform(-PRINCIPAL_JITTER, PRINCIPAL_JITTER, 2)
    side = float(rng.uniform(-1.0, 1.0))
    return CameraDraw(low + share * (high - low), pitch, hfov, (float(du), float(dv)),
                      side * variant.side_m)


def salad_seeds(split: str, count: int, start: int = 0) -> range:
    """Seeds start .. start + count - 1 of a split ('train', 'test' or 'val')."""
    if split not in SPLITS:
        raise ValueError(f'split must be one of {", ".join(SPLITS)}, got {split!r}')
    if start < 0 or count < 0 or start + count > SALAD_SEED_SPAN:
        raise ValueError(f'seeds {start}..{start + count - 1} are outside the split\'s '
                         f'0..{SALAD_SEED_SPAN - 1}')
    return range(SPLITS[split] + start, SPLITS[split] + start + count)


def drive_camera(seed: int, frames: int, size: tuple[int, int] = DEFAULT_SIZE,
                 randomise: bool = True, variant: DriveVariant = SEEDS_OWN) -> SimCamera:
    """The seed's simulator (long enough for `frames` frames FRAME_STRIDE sweeps apart) and
    the camera on it (camera_for_seed)."""
    if not 1 <= frames <= (MAX_SWEEPS - 1) // FRAME_STRIDE + 1:
        raise ValueError(f'frames must be within 1..{(MAX_SWEEPS - 1) // FRAME_STRIDE + 1}, '
                         f'got {frames}')
    scenario = scenario_for_seed(seed)
    sim = Simulator(seed, sweeps=(frames - 1) * FRAME_STRIDE + 1, sensor=scenario['sensor'],
                    topology=scenario['topology'], **variant.road(seed))
    draw = camera_for_seed(seed, randomise, variant)
    width, height = size
    return SimCamera(sim, width, height, T_cloud_camera=draw.extrinsic(sim.mount.z),
                     K=draw.intrinsics((width, height)))


def visible_lanes(camera: SimCamera, k: int) -> tuple[CameraImage, list[np.ndarray]]:
    """Sweep k's image and the 3D GT of the lane pieces it shows, each (N, 3) in the optical
    frame, near end first."""
    image = camera.render(k)
    _, pieces = sim_image_labels(camera.sim, camera.calibration(), image)
    to_camera = np.linalg.inv(image.camera_to_odom)
    return image, [p @ to_camera[:3, :3].T + to_camera[:3, 3] for p in pieces]


def simulated_samples(seed: int, frames: int, size: tuple[int, int] = DEFAULT_SIZE,
                      randomise: bool = True, variant: DriveVariant = SEEDS_OWN
                      ) -> Iterator[CameraLaneSample]:
    """`frames` images of the seed's drive, FRAME_STRIDE sweeps apart, with their visible
    lanes. randomise: the seed's own camera (camera_for_seed, as the variant draws it), else the
    fixed one."""
    camera = drive_camera(seed, frames, size, randomise, variant)
    # the mount is known: the LiDAR frame is level, sim.mount.z over the road the car stands on
    T_road_camera = camera.T_cloud_camera.copy()
    T_road_camera[2, 3] += camera.sim.mount.z
    road = RoadPlane.from_extrinsic(T_road_camera)
    for k in range(0, frames * FRAME_STRIDE, FRAME_STRIDE):
        image, lanes = visible_lanes(camera, k)
        yield CameraLaneSample(image.rgb, camera.K.copy(), lanes, f'sim seed {seed} sweep {k}',
                               road)
