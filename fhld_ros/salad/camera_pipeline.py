"""The core that camera_lane_detector and `fhld replay --detector salad` both drive: camera
images in, lanes out, with no rclpy.

    pipeline.receive_camera_info(msg)  # its newest good message gives each image's intrinsics
    pipeline.receive_image(msg)        # decoded, checked; kept when due, else skipped
    out = pipeline.detect()            # None unless an image is waiting: SALAD on it
    lane_messages(out)                 # what is published (lane_output.py)

An image is due when its stamp is at least 0.9 / rate_hz past the last detected one (or older:
time went back), as LanePipeline decides on sweeps: the node and a replay of its input detect
the same images. Only the newest due image waits for detection; one it replaces before it was
detected is counted as overtaken (a drop). A malformed image or camera_info raises ValueError
naming the problem from add_*; receive_* counts it and returns it instead.

Lanes come out in params.output_frame through params.camera_to_output, else in the image's
frame (the camera's optical frame: x right, y down, z forward). Ids are kept from image to image
and the ego lane's bounds found in the camera's own forward-left-up frame (the optical frame
turned: x forward, y left), whatever the output frame. The bev_window outline is the ground the
model saw up to the decoder's depth (annotation/footprint.py) on the plane the lanes span, or a
level road params.camera_height_m below the camera when they span none. With
params.road_plane_m the near lanes take their depth from output_frame's z = 0 plane, the road
(road_plane.py), and the outline lies on it (on the lanes' plane first where road_plane_pitch
is 'image': the mount's pitch is not trusted).
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from fhld_ros.annotation.footprint import camera_footprint
from fhld_ros.camera.calibration import CameraCalibration, seen_box
from fhld_ros.camera.lens import Lens
from fhld_ros.errors import ConfigError
from fhld_ros.lane_output import LaneIdTracker, LaneOutput, ego_lane_bounds
from fhld_ros.pipeline import DUE_FRACTION
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT
from fhld_ros.salad.config import HEIGHT_RANGE_M, WIDE_MOUNT_HEIGHTS_M, SaladConfig
from fhld_ros.salad.detector import SaladDetector
from fhld_ros.salad.lanes_road import OPTICAL_TO_FLU, height_over, lanes_pitch, lanes_plane
from fhld_ros.salad.parameters import CameraParams
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.virtual_camera import VirtualCamera
from msg_adapters.camera import camera_info_values, msg_to_image
from msg_adapters.family import stamp_to_ns
from msg_adapters.odometry import euler_to_matrix

EGO_REACH_M = 15.0  # a camera sees the road from metres ahead: ego bounds are taken this far
MOUNT_MARGIN_M = 0.1  # beyond the trained heights by more, the near depth is off (salad.md)
REGION_PX_PER_UNIT = 1000.0  # the region the model sees, as a camera: pixels per tan(angle)
# image_proc's image_rect and image_rect_color, a driver's rect_image or image_rectified
RECTIFIED_NAME = re.compile(r'(^|_)rect(ified)?(_|$)')


class CameraLaneDetector(Protocol):
    """SaladDetector's shape: (H, W, 3) uint8 RGB, K, the road plane if known and the lens
    distortion if any -> lanes ((N, 3) optical frame) and scores; its config (virtual camera,
    decoder depth) and the last call's stage timings."""

    cfg: SaladConfig
    timings_ms: dict[str, float]

    def __call__(self, image: np.ndarray, intrinsics: np.ndarray, road: RoadPlane | None = None,
                 distortion: Lens | np.ndarray | None = None
                 ) -> tuple[list[np.ndarray], np.ndarray]: ...


@dataclass(frozen=True)
class CameraIntrinsics:
    """The newest good camera_info: the image size it describes, K, its lens distortion (None:
    none) and its frame."""

    width: int
    height: int
    K: np.ndarray
    lens: Lens | None
    frame_id: str


@dataclass
class CameraImage:
    """One decoded image with the intrinsics it came with, waiting for detection."""

    stamp_ns: int
    frame_id: str
    rgb: np.ndarray  # (H, W, 3) uint8
    camera: CameraIntrinsics


@dataclass
class ImageIntake:
    """What one image did: kept for detection (due; replaced: in place of a due one that was
    not detected yet, a drop), skipped (rate_hz), or why it was dropped."""

    stamp_ns: int | None = None
    due: bool = False
    replaced: bool = False
    dropped: ValueError | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)


def load_camera_detector(params: CameraParams) -> SaladDetector:
    """SaladDetector as the parameters ask: their checkpoint ('' = the shipped weights),
    model_threads, model_runtime, flip_average, road_profile, min_paint_contrast and
    double_lines; ConfigError naming the file when it is missing or unusable."""
    checkpoint = params.checkpoint
    try:
        return SaladDetector(checkpoint or DEFAULT_SALAD_CHECKPOINT, params.model_threads,
                             params.model_runtime, params.flip_average, params.road_profile,
                             params.min_paint_contrast, params.double_lines)
    except ConfigError as exc:
        if checkpoint:
            raise
        raise ConfigError(f'{exc} (the shipped weights; name others with the checkpoint '
                          'parameter, or fhld replay --checkpoint)') from exc


def trained_heights(info: dict[str, Any]) -> tuple[float, float] | None:
    """The camera heights (m) of the simulated drives the weights were last trained on; None
    when they saw no drives, or datasets whose mounts are unknown."""
    meta = info.get('meta', {})
    if not meta.get('drives') or meta.get('datasets'):
        return None
    low, high = meta.get('camera_heights_m', HEIGHT_RANGE_M)
    return float(low), float(high)


def mount_warning(info: dict[str, Any], road: RoadPlane | None) -> str | None:
    """What to do when the known mount's camera sits outside the heights the weights were
    trained on (their lanes then lie as if it sat within them, docs/salad.md), or None."""
    heights = trained_heights(info)
    if road is None or heights is None:
        return None
    height, (low, high) = road.height_m, heights
    if low - MOUNT_MARGIN_M <= height <= high + MOUNT_MARGIN_M:
        return None
    wide_low, wide_high = WIDE_MOUNT_HEIGHTS_M
    advice = ('checkpoint:=salad_wide_mount (trained on cameras '
              f'{wide_low:.1f}-{wide_high:.1f} m up)' if wide_low <= height <= wide_high else
              f'weights fine-tuned for it (fhld salad-train OUT --init <these weights> '
              f'--camera-height {height - 0.2:.1f} {height + 0.2:.1f})')
    return (f'camera_to_output puts the camera {height:.2f} m above the road, and these SALAD '
            f'weights were trained on cameras {low:.1f}-{high:.1f} m up: their lanes will lie '
            f'as if it were within that range; use {advice}')


def distortion_notice(image_topic: str, camera_info_topic: str, lens: Lens
                      ) -> tuple[str, str]:
    """(text, 'info' or 'warning') said once when camera_info has lens distortion: removed from
    each image; a warning when the image topic's name says its images are rectified already
    (they would be undistorted twice)."""
    text = (f'{camera_info_topic} has lens distortion ({lens}): removed from each image as it '
            'is resampled')
    names = [n for n in image_topic.split('/') if n and n != 'compressed']
    if names and RECTIFIED_NAME.search(names[-1]):
        return (f'{text}; {image_topic} looks rectified already: if it is, set '
                "image_rectified:=true (intrinsics from camera_info's P, no distortion)",
                'warning')
    return f'{text} (rectified images: image_rectified:=true)', 'info'


def check_camera_info(msg: Any, rectified: bool = False) -> CameraIntrinsics:
    """camera_info -> CameraIntrinsics; ValueError naming the problem (distortion model, an
    image size or K that no camera has: K all zero is an uncalibrated camera's). Rectified
    images take P's left 3x3 for K and no distortion (camera_info_values)."""
    width, height, K, model, d, frame_id = camera_info_values(msg, rectified)
    name = 'P' if rectified else 'K'
    if width <= 0 or height <= 0:
        raise ValueError(f'camera_info size {width}x{height} is not positive')
    if not np.all(np.isfinite(K)):
        raise ValueError(f'camera_info {name} is not finite')
    if not np.any(K):
        raise ValueError(f'camera_info {name} is all zero (an uncalibrated camera)')
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f'camera_info {name} has focal lengths {K[0, 0]:g}, {K[1, 1]:g}; both '
                         'must be > 0')
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or np.any(K[2] != [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ValueError(f'camera_info {name} is not a pinhole without skew ([fx 0 cx; 0 fy '
                         'cy; 0 0 1])')
    try:
        lens = Lens.from_camera_info(model, d)
    except ValueError as exc:
        raise ValueError(f'camera_info {exc} (rectified images: image_rectified:=true)'
                         ) from None
    return CameraIntrinsics(width, height, K, lens, frame_id)


def seen_region(camera: CameraIntrinsics, virtual: VirtualCamera) -> CameraCalibration | None:
    """The part of the image the model sees (where the image, its lens undone, and the virtual
    camera it is resampled to overlap) as a pinhole camera of its own, whose image corners are
    that part's corners; None when they do not overlap."""
    f = virtual.focal
    seen_low, seen_high = seen_box(camera.width, camera.height, camera.K, camera.lens)
    low = np.maximum(seen_low, [-virtual.cx / f, -virtual.cy / f])
    high = np.minimum(seen_high, [(virtual.width - virtual.cx) / f,
                                  (virtual.height - virtual.cy) / f])
    if np.any(high - low <= 1.0 / REGION_PX_PER_UNIT):
        return None
    size = np.round((high - low) * REGION_PX_PER_UNIT)
    scale = size / (high - low)
    k = np.array([[scale[0], 0.0, -low[0] * scale[0]], [0.0, scale[1], -low[1] * scale[1]],
                  [0.0, 0.0, 1.0]])
    return CameraCalibration(int(size[0]), int(size[1]), k, np.zeros(5), np.eye(4))


def mount_plane(road: RoadPlane) -> tuple[np.ndarray, np.ndarray]:
    """(up normal, point) of the known mount's road, camera forward-left-up frame."""
    down = OPTICAL_TO_FLU @ np.asarray(road.normal)
    return -down, down * road.height_m


class CameraPipeline:
    """camera_info + images -> SALAD -> lanes in the output frame, with stable ids."""

    def __init__(self, params: CameraParams, detector: CameraLaneDetector) -> None:
        self.params = params
        self.detector = detector
        self.min_interval_ns = int(DUE_FRACTION * 1e9 / params.rate_hz)
        self.T_output_camera = euler_to_matrix(*params.camera_to_output)
        self.road = (RoadPlane.from_extrinsic(self.T_output_camera, params.road_plane_m,
                                              params.road_plane_pitch == 'image')
                     if params.road_plane_m > 0 else None)
        self.mount_plane = None if self.road is None else mount_plane(self.road)
        self.mount_warning = mount_warning(getattr(detector, 'info', {}), self.road)
        self.camera: CameraIntrinsics | None = None
        self.camera_problem = 'no camera_info received yet'
        self.pending: CameraImage | None = None
        self.last_detected_ns: int | None = None
        self.ids = LaneIdTracker()
        self.output_frame: str | None = None
        self.counters = {'images': 0, 'camera_infos': 0, 'detections': 0, 'images_skipped': 0,
                         'images_overtaken': 0, 'bad_images': 0, 'bad_camera_info': 0,
                         'lanes_unpainted': 0}

    def receive_camera_info(self, msg: Any) -> ValueError | None:
        """add_camera_info; a bad message is counted (bad_camera_info) and returned: images
        are refused, naming it, until a good one comes."""
        try:
            self.add_camera_info(msg)
        except ValueError as exc:
            self.camera, self.camera_problem = None, f'the newest camera_info is bad: {exc}'
            self.counters['bad_camera_info'] += 1
            return exc.with_traceback(None)  # its frames would keep the message alive
        return None

    def add_camera_info(self, msg: Any) -> None:
        self.camera = check_camera_info(msg, self.params.image_rectified)
        self.counters['camera_infos'] += 1

    def receive_image(self, msg: Any) -> ImageIntake:
        """add_image, with a bad image dropped and counted (bad_images), never raised."""
        try:
            return self.add_image(msg)
        except ValueError as exc:
            self.counters['bad_images'] += 1
            # without its traceback: its frames hold the image (as LanePipeline.receive_cloud)
            return ImageIntake(dropped=exc.with_traceback(None))

    def add_image(self, msg: Any) -> ImageIntake:
        """Decode and check one image; it waits for detection when due (replacing a waiting
        one, counted as overtaken), else it is skipped; msg: a sensor_msgs/Image or
        CompressedImage. ValueError (naming the problem) for an unsupported encoding or
        compressed format, data that do not hold the image, no usable camera_info, an image
        size other than the camera_info's, or no frame to publish in."""
        start = time.perf_counter()
        if self.camera is None:
            raise ValueError(self.camera_problem)
        rgb = msg_to_image(msg)
        camera = self.camera
        if (rgb.shape[1], rgb.shape[0]) != (camera.width, camera.height):
            raise ValueError(f'image is {rgb.shape[1]}x{rgb.shape[0]}, its camera_info says '
                             f'{camera.width}x{camera.height}')
        frame = str(msg.header.frame_id) or camera.frame_id
        if not frame and not self.params.output_frame:
            raise ValueError('image and camera_info have an empty frame_id (and no '
                             'output_frame is set)')
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self.counters['images'] += 1
        timings = {'image_decode_ms': (time.perf_counter() - start) * 1e3}
        last = self.last_detected_ns
        if last is not None and 0 <= stamp_ns - last < self.min_interval_ns:
            self.counters['images_skipped'] += 1
            return ImageIntake(stamp_ns, timings_ms=timings)
        replaced = self.pending is not None
        if replaced:
            self.counters['images_overtaken'] += 1
        self.pending = CameraImage(stamp_ns, frame, rgb, camera)
        return ImageIntake(stamp_ns, due=True, replaced=replaced, timings_ms=timings)

    @property
    def detection_due(self) -> bool:
        return self.pending is not None

    def due_image(self) -> CameraImage | None:
        """The image to detect on now (taken: a newer one may come meanwhile), None when none
        waits. Cheap: the node calls it under its lock and detect_image outside."""
        image, self.pending = self.pending, None
        if image is not None:
            if self.last_detected_ns is not None and image.stamp_ns < self.last_detected_ns:
                self.ids.reset()  # time went back (a bag played again): other lanes
            self.last_detected_ns = image.stamp_ns
        return image

    def detect_image(self, image: CameraImage) -> LaneOutput:
        """SALAD on one image; lanes above score_threshold, in the output frame."""
        lanes_optical, scores = self.detector(image.rgb, image.camera.K, self.road,
                                              image.camera.lens)
        start = time.perf_counter()
        keep = [i for i, score in enumerate(scores) if score >= self.params.score_threshold]
        confidences = np.asarray(scores, dtype=np.float64)[keep]
        lanes_flu = [np.asarray(lanes_optical[i], dtype=np.float64) @ OPTICAL_TO_FLU.T
                     for i in keep]
        frame = self.params.output_frame or image.frame_id
        if frame != self.output_frame:
            self.ids.reset()  # ids follow lanes in one frame
            self.output_frame = frame
        # the camera's forward-left-up frame -> the output frame
        T = self.T_output_camera.copy()
        T[:3, :3] = T[:3, :3] @ OPTICAL_TO_FLU.T
        lanes = [lane @ T[:3, :3].T + T[:3, 3] for lane in lanes_flu]
        left, right = ego_lane_bounds(lanes_flu, EGO_REACH_M)
        plane = lanes_plane(lanes_flu)
        pitch = lanes_pitch([lanes_optical[i] for i in keep], self.detector.cfg.camera)
        outline = self.outline(image.camera, plane)
        self.counters['detections'] += 1
        self.counters['lanes_unpainted'] += self.detector.lanes_unpainted
        timings = dict(self.detector.timings_ms)
        timings['output_ms'] = (time.perf_counter() - start) * 1e3
        return LaneOutput(
            stamp_ns=image.stamp_ns, frame_id=frame, lanes=lanes, confidences=confidences,
            ids=self.ids.assign(lanes_flu), outline=outline @ T[:3, :3].T + T[:3, 3],
            ego_left=None if left is None else lanes[left],
            ego_right=None if right is None else lanes[right], timings_ms=timings,
            lanes_plane_height_m=None if plane is None else height_over(plane),
            lanes_pitch_deg=None if pitch is None else float(np.degrees(pitch)))

    def outline(self, camera: CameraIntrinsics,
                lanes_ground: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """(5, 3) closed outline, camera forward-left-up frame, of the ground the model saw up
        to the decoder's depth, on the known mount's road, else lanes_ground (the plane the
        lanes span, lanes_plane()), else a level road (see the module doc); lanes_ground first
        where the mount's pitch is not trusted (road_plane_pitch image); the camera's position
        five times when it saw no ground (a camera looking up)."""
        cfg = self.detector.cfg
        region = seen_region(camera, cfg.camera)
        T_flu_optical = np.eye(4)
        T_flu_optical[:3, :3] = OPTICAL_TO_FLU
        level = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -self.params.camera_height_m]))
        planes = (self.mount_plane, lanes_ground, level)
        if self.road is not None and self.road.pitch_from_image:
            planes = (lanes_ground, self.mount_plane, level)
        for plane in planes:
            if plane is None or region is None:
                continue
            ground = camera_footprint(region, T_flu_optical, *plane, cfg.max_depth_m)
            if ground is not None:
                return ground
        return np.zeros((5, 3))

    def detect(self) -> LaneOutput | None:
        """due_image + detect_image; None when no image waits."""
        image = self.due_image()
        return None if image is None else self.detect_image(image)
