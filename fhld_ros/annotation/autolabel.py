"""3D lanes of a drive from the 2D lane labels of its images and its LiDAR sweeps: the five
steps of ONCE-3DLanes section 3.2 per labelled image (docs/annotation.md).

For an image at stamp t the sweeps from t - PAST_S to t + FUTURE_S are registered with the
odometry (as the node accumulates them; an offline labeller may also look ahead, where the
road the camera sees gets its dense returns), reduced to the ground (ground.py), projected
into the image with the calibration, gathered inside each broadened label (lane_regions.py)
and recovered as 3D lanes (recovery.py). Without odometry each image gets its nearest sweep.
"""
from __future__ import annotations

import collections
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from fhld_ros.annotation.footprint import camera_footprint, ground_plane
from fhld_ros.annotation.ground import GroundSurface, below_sensor, segment_ground
from fhld_ros.annotation.lane_regions import LaneMembers, lane_members
from fhld_ros.annotation.recovery import recover_lane
from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.labels2d import ImageLabels
from fhld_ros.geometry import pose_at, resample_polyline
from fhld_ros.intensity import CONTRAST, GROUND_LEVEL, IntensityEncoder

PAST_S = 0.5
FUTURE_S = 2.0
MAX_RANGE_M = 60.0  # labels are lifted up to this depth
REACH_PERCENTILE = 99.0  # the output window reaches as far as this share of the ground in view
SEED_AHEAD_M = 6.0  # ground grows from the road this far ahead of the camera
MIN_LANE_M = 1.0  # shorter recovered pieces are dropped
LABEL_STEP_PX = 2.0  # labels are resampled this finely (regions, and rays cast from them) ...
LABEL_SMOOTH_SAMPLES = 9  # ... and averaged over this many samples: far away a pixel of
# labelling error is decimetres on the road, and a region a few pixels wide misses the paint
SURFACE_SUPPORT_M = 3.0  # a ray's ground hit counts with a ground return this close to it
SURFACE_POINTS = 100_000  # the ground surface is fitted to about this many returns at most


@dataclass
class Sweep:
    stamp_ns: int
    xyz: np.ndarray  # (N, 3) float64 coarse-ground returns in the drive frame (odom or cloud)
    contrast: np.ndarray  # (N,) intensity over the sweep's road level
    index: int  # the sweep's number in the drive


@dataclass
class LabelledImage:
    stamp_ns: int
    frame_id: str  # the output frame: odometry's, else the cloud's
    T_out_camera: np.ndarray  # (4, 4) camera pose in the output frame
    lanes: list[np.ndarray]  # (K, 3) in the output frame
    ids: list[int]
    outline: np.ndarray  # (5, 3) the ground the camera sees, as far as its ground returns reach
    labels: ImageLabels
    ground: np.ndarray  # (N, 3) ground returns the camera sees, output frame
    ground_contrast: np.ndarray  # (N,)


@dataclass
class AutolabelCounts:
    images: int = 0  # labelled images lifted to 3D
    lanes: int = 0
    labels_without_image: int = 0  # label files whose stamp no image or sweep in the bag has
    images_without_labels: int = 0
    images_without_points: int = 0  # the camera saw no ground return at all
    label_points_outside_image: int = 0


class PoseTrack:
    """All odometry poses of a drive (cloud frame -> odometry frame), interpolated."""

    def __init__(self, stamps: np.ndarray, poses: np.ndarray, frame_id: str) -> None:
        order = np.argsort(stamps, kind='stable')
        self.stamps, self.poses, self.frame_id = stamps[order], poses[order], frame_id

    def at(self, stamp_ns: int) -> np.ndarray | None:
        return pose_at(self.stamps, self.poses, stamp_ns, max_gap_ns=None)


class Autolabeler:
    """Feed sweeps in stamp order; labelled images come out once their sweeps are in."""

    def __init__(self, calib: CameraCalibration, labels: dict[int, ImageLabels],
                 image_stamps: list[int], poses: PoseTrack | None,
                 past_s: float = PAST_S, future_s: float = FUTURE_S) -> None:
        self.calib, self.poses = calib, poses
        self.past_ns, self.future_ns = int(past_s * 1e9), int(future_s * 1e9)
        if poses is None:  # one sweep per image: the nearest
            self.past_ns = self.future_ns = 50_000_000
        self.counts = AutolabelCounts()
        self.pending: collections.deque[ImageLabels] = collections.deque()
        self.sweeps: collections.deque[Sweep] = collections.deque()
        self.encoder = IntensityEncoder(CONTRAST)
        self.cloud_frame: str | None = None
        self.n_sweeps = 0
        matched = _match_stamps(labels, image_stamps)
        self.counts.images_without_labels = len(set(image_stamps) - set(matched.values()))
        self.counts.labels_without_image = len(set(labels) - set(matched))
        for label_stamp in sorted(matched, key=matched.get):
            image = labels[label_stamp]
            self.pending.append(ImageLabels(matched[label_stamp], image.frame_id,
                                            image.image_size, image.lanes))
        self.stamps = [image.stamp_ns for image in self.pending]  # the images to be labelled

    def add_sweep(self, stamp_ns: int, frame_id: str, xyz: np.ndarray, intensity: np.ndarray
                  ) -> Iterator[LabelledImage]:
        """One decoded sweep (cloud frame); yields the images it completes."""
        if self.cloud_frame is None:
            self.cloud_frame = frame_id
        contrast = self.encoder(xyz, intensity) / np.float32(GROUND_LEVEL)
        keep = below_sensor(xyz)
        pose = np.eye(4) if self.poses is None else self.poses.at(stamp_ns)
        if pose is not None:
            pts = xyz[keep].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            self.sweeps.append(Sweep(stamp_ns, pts, contrast[keep], self.n_sweeps))
        self.n_sweeps += 1
        yield from self._ready(stamp_ns)

    def finish(self) -> Iterator[LabelledImage]:
        yield from self._ready(None)

    def _ready(self, newest_ns: int | None) -> Iterator[LabelledImage]:
        while self.pending and (newest_ns is None or
                                newest_ns >= self.pending[0].stamp_ns + self.future_ns):
            image = self.pending.popleft()
            result = self._label(image)
            if result is not None:
                yield result
        oldest = self.pending[0].stamp_ns - self.past_ns if self.pending else newest_ns
        while self.sweeps and oldest is not None and self.sweeps[0].stamp_ns < oldest:
            self.sweeps.popleft()

    def _label(self, image: ImageLabels) -> LabelledImage | None:
        calib = self.calib
        pose = np.eye(4) if self.poses is None else self.poses.at(image.stamp_ns)
        use = [s for s in self.sweeps
               if image.stamp_ns - self.past_ns <= s.stamp_ns <= image.stamp_ns + self.future_ns]
        if pose is None or not use:
            self.counts.images_without_points += 1
            return None
        if self.poses is None:  # the nearest sweep alone
            use = [min(use, key=lambda s: abs(s.stamp_ns - image.stamp_ns))]
        xyz = np.concatenate([s.xyz for s in use])
        contrast = np.concatenate([s.contrast for s in use])
        sweep = np.concatenate([np.full(s.xyz.shape[0], s.index) for s in use])
        T_out_camera = pose @ calib.camera_in_cloud
        forward = _horizontal(T_out_camera[:3, 2])
        ground = segment_ground(xyz, T_out_camera[:2, 3] + SEED_AHEAD_M * forward)
        xyz, contrast, sweep = xyz[ground], contrast[ground], sweep[ground]
        T_camera_out = np.linalg.inv(T_out_camera)
        cam = xyz @ T_camera_out[:3, :3].T + T_camera_out[:3, 3]
        uv, depth, inside = calib.project_camera(cam)
        inside &= depth <= MAX_RANGE_M
        if not inside.any():
            self.counts.images_without_points += 1
            return None
        idx = np.flatnonzero(inside)
        uv, depth = uv[idx], depth[idx]
        # the window claims what the LiDAR covers: at the end of a drive no later sweep has
        # reached the far road the camera sees, and nothing is lifted there
        reach = float(np.percentile(depth, REACH_PERCENTILE))
        regions, label_rays = [], []
        for label in image.lanes:
            in_image = (label.uv[:, 0] >= 0) & (label.uv[:, 0] <= calib.width) & \
                (label.uv[:, 1] >= 0) & (label.uv[:, 1] <= calib.height)
            self.counts.label_points_outside_image += int((~in_image).sum())
            if in_image.sum() >= 2:
                line = uniform_filter1d(resample_polyline(label.uv[in_image], LABEL_STEP_PX),
                                        LABEL_SMOOTH_SAMPLES, axis=0, mode='nearest')
                regions.append((label.id, lane_members(uv, depth, line, float(calib.K[0, 0]))))
                label_rays.append(calib.pixel_rays(line) @ T_out_camera[:3, :3].T)
        owner = _nearest_region([members for _, members in regions], uv.shape[0])
        surface = GroundSurface(xyz[::max(1, xyz.shape[0] // SURFACE_POINTS)])
        lanes, ids = [], []
        for k, (label_id, members) in enumerate(regions):
            own = owner[members.index] == k
            rows = idx[members.index[own]]
            rays = (T_out_camera[:3, 3], label_rays[k])
            hits, support = surface.cast(*rays)
            hits = hits[support <= SURFACE_SUPPORT_M]
            for piece in recover_lane(xyz[rows], members.t[own], contrast[rows], sweep[rows],
                                      rays, hits):
                if np.linalg.norm(np.diff(piece[:, :2], axis=0), axis=1).sum() >= MIN_LANE_M:
                    lanes.append(piece)
                    ids.append(label_id)
        self.counts.images += 1
        self.counts.lanes += len(lanes)
        # the window is what the camera sees of the ground plane of its returns in view, so
        # that eval does not count lines outside the image as missed
        outline = camera_footprint(calib, T_out_camera, *ground_plane(xyz[idx]), reach)
        if outline is None:  # it sees too little of that plane: the square its returns reach
            outline = window_outline(T_out_camera[:2, 3], forward, reach,
                                     float(np.median(xyz[idx, 2])))
        frame = self.cloud_frame if self.poses is None else self.poses.frame_id
        return LabelledImage(image.stamp_ns, str(frame), T_out_camera, lanes, ids, outline,
                             image, xyz[idx], contrast[idx])


def _nearest_region(regions: list[LaneMembers], n: int) -> np.ndarray:
    """(n,) index of the region each return belongs to (-1: none). Regions overlap where lines
    run close (a double line's stripes ~0.3 m apart): a return goes to the nearest label, so
    each stripe stays with its own line instead of pulling the other's centre towards it."""
    best = np.full(n, np.inf)
    owner = np.full(n, -1)
    for k, members in enumerate(regions):
        dist = np.abs(members.offset_px)
        nearer = dist < best[members.index]
        best[members.index[nearer]] = dist[nearer]
        owner[members.index[nearer]] = k
    return owner


def window_outline(camera_xy: np.ndarray, forward: np.ndarray, reach_m: float,
                   z: float) -> np.ndarray:
    """The square from the camera to reach_m ahead, reach_m wide: rear-right, front-right,
    front-left, rear-left, back to the first (bev.py's corner order)."""
    left = np.array([-forward[1], forward[0]])
    half = reach_m / 2
    corners = [camera_xy + a * forward * reach_m + b * left * half
               for a, b in ((0, -1), (1, -1), (1, 1), (0, 1), (0, -1))]
    return np.column_stack([np.array(corners), np.full(5, z)])


def _horizontal(v: np.ndarray) -> np.ndarray:
    h = np.array([v[0], v[1]], dtype=np.float64)
    n = np.linalg.norm(h)
    return h / n if n > 1e-9 else np.array([1.0, 0.0])


def _match_stamps(labels: dict[int, ImageLabels], image_stamps: list[int],
                  tolerance_ns: int = 5_000_000) -> dict[int, int]:
    """Label stamp -> the image stamp it labels (exact, else nearest within tolerance)."""
    stamps = np.array(sorted(set(image_stamps)), dtype=np.int64)
    out = {}
    if stamps.size == 0:
        return out
    for stamp in labels:
        k = int(np.clip(np.searchsorted(stamps, stamp), 1, len(stamps) - 1)) \
            if len(stamps) > 1 else 0
        best = min((stamps[max(k - 1, 0)], stamps[k]), key=lambda s: abs(int(s) - stamp))
        if abs(int(best) - stamp) <= tolerance_ns:
            out[stamp] = int(best)
    return out
