"""A camera's intrinsics and its pose relative to the LiDAR, and projection of LiDAR points into
its image (OpenCV's pinhole model and a lens of `lens.py`; pixel (0, 0)'s centre is at
u = v = 0).

Read from a bag (`/camera/camera_info` + `/tf_static`) or from a calibration YAML
(docs/annotation.md, "Calibration").
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fhld_ros.camera.lens import MODELS, PLUMB_BOB, Lens, as_lens
from fhld_ros.errors import ConfigError
from msg_adapters.camera import camera_info_values, tf_transforms

MIN_DEPTH_M = 0.1  # points nearer the image plane than this are not projected
BORDER_SAMPLES = 65  # points per image side where seen_box undistorts the border


@dataclass(frozen=True)
class CameraCalibration:
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    D: np.ndarray  # distortion_model's coefficients (plumb_bob: k1 k2 p1 p2 k3); zeros: none
    T_camera_cloud: np.ndarray  # (4, 4): cloud (LiDAR) frame -> camera optical frame
    camera_frame: str = 'camera'
    cloud_frame: str = 'lidar'
    distortion_model: str = PLUMB_BOB  # camera_info's name (lens.py)

    def __post_init__(self) -> None:
        problem = _problem(self)
        if problem:
            raise ConfigError(f'camera calibration: {problem}')

    def to_camera(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) cloud-frame points -> (N, 3) camera optical frame."""
        return np.asarray(xyz, dtype=np.float64) @ self.T_camera_cloud[:3, :3].T + \
            self.T_camera_cloud[:3, 3]

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cloud-frame points -> pixels (N, 2), depth (N,) along the optical axis, and whether
        each lands in the image in front of the camera."""
        return self.project_camera(self.to_camera(xyz))

    def project_camera(self, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The same for points already in the camera optical frame."""
        depth = cam[:, 2]
        ahead = depth > MIN_DEPTH_M
        safe = np.where(ahead, depth, 1.0)
        x, y = cam[:, 0] / safe, cam[:, 1] / safe
        lens = self.lens
        if lens is not None:
            # far outside the field of view a lens's polynomial folds back into the image
            ahead &= lens.unfolded(x, y, self.max_r2)
            x, y = lens.distort(x, y)
        K = self.K
        uv = np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)
        inside = ahead & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < self.height)
        return uv, depth, inside

    def pixel_rays(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit directions in the camera optical frame (distortion
        undone by fixed-point iteration, as OpenCV's undistortPoints does)."""
        rays = np.column_stack([undistort(uv, self.K, self.lens), np.ones(len(uv))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    @property
    def lens(self) -> Lens | None:
        return Lens.from_camera_info(self.distortion_model, self.D)

    @property
    def max_r2(self) -> float:
        """Squared normalised radius of the image corners (undistorted estimate)."""
        return corner_r2(self.width, self.height, self.K)

    @property
    def camera_in_cloud(self) -> np.ndarray:
        """The camera's pose in the cloud frame (4, 4)."""
        return np.linalg.inv(self.T_camera_cloud)

    # -- files and messages ------------------------------------------------------------------
    @classmethod
    def from_yaml(cls, path: str | Path) -> CameraCalibration:
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f'--calib {path}: cannot read it ({exc.__class__.__name__}: '
                              f'{str(exc).splitlines()[0]})') from exc
        if not isinstance(data, dict):
            raise ConfigError(f'--calib {path}: expected a mapping with width, height, K, '
                              'T_camera_cloud')
        missing = [k for k in ('width', 'height', 'K', 'T_camera_cloud') if k not in data]
        if missing:
            raise ConfigError(f'--calib {path}: missing {", ".join(missing)}')
        unknown = sorted(set(data) - {'width', 'height', 'K', 'D', 'distortion_model',
                                      'T_camera_cloud', 'camera_frame', 'cloud_frame'})
        if unknown:
            raise ConfigError(f'--calib {path}: unknown key {unknown[0]!r}')
        try:
            model = str(data.get('distortion_model', PLUMB_BOB))
            lens = Lens.from_camera_info(model, data.get('D') or [])
            if lens is None:  # keeps the file's model, D of its length (_problem names a bad one)
                d = np.zeros(MODELS.get(model, (0, 5))[1])
            else:
                d, model = _coefficients(lens)
            return cls(int(data['width']), int(data['height']),
                       np.asarray(data['K'], dtype=np.float64).reshape(3, 3), d,
                       np.asarray(data['T_camera_cloud'], dtype=np.float64).reshape(4, 4),
                       str(data.get('camera_frame', 'camera')),
                       str(data.get('cloud_frame', 'lidar')), model)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f'--calib {path}: {exc}') from exc

    def to_yaml(self, path: str | Path) -> None:
        data = {'width': self.width, 'height': self.height,
                'K': [float(v) for v in self.K.ravel()], 'D': [float(v) for v in self.D],
                'distortion_model': self.distortion_model,
                'T_camera_cloud': [[float(v) for v in row] for row in self.T_camera_cloud],
                'camera_frame': self.camera_frame, 'cloud_frame': self.cloud_frame}
        Path(path).write_text('# fhld camera calibration (docs/annotation.md)\n' +
                              yaml.safe_dump(data, sort_keys=False, default_flow_style=None))

    @classmethod
    def from_messages(cls, camera_info: Any, tf_static: list[Any], cloud_frame: str
                      ) -> CameraCalibration:
        """From a CameraInfo and the /tf_static messages: the transform may be stored either
        way round between the cloud frame and the camera_info's frame."""
        width, height, K, model, D, camera_frame = camera_info_values(camera_info)
        if not camera_frame:
            raise ConfigError('/camera/camera_info has an empty frame_id')
        T_camera_cloud = None
        for msg in tf_static:
            for parent, child, T_parent_child in tf_transforms(msg):
                if (parent, child) == (cloud_frame, camera_frame):
                    T_camera_cloud = np.linalg.inv(T_parent_child)
                elif (parent, child) == (camera_frame, cloud_frame):
                    T_camera_cloud = T_parent_child
        if T_camera_cloud is None:
            raise ConfigError(f'no /tf_static transform between {cloud_frame} (the clouds) and '
                              f'{camera_frame} (the camera); give --calib YAML')
        try:
            lens = Lens.from_camera_info(model, D)
        except ValueError as exc:
            raise ConfigError(f'/camera/camera_info: {exc}') from exc
        d, model = _coefficients(lens)
        return cls(int(width), int(height), np.asarray(K, dtype=np.float64).reshape(3, 3), d,
                   T_camera_cloud, camera_frame, cloud_frame, model)


def corner_r2(width: int, height: int, K: np.ndarray) -> float:
    """Squared normalised radius of a width x height image's corners (undistorted estimate):
    far beyond it the distortion polynomial folds back into the image."""
    corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], dtype=np.float64)
    x = (corners[:, 0] - K[0, 2]) / K[0, 0]
    y = (corners[:, 1] - K[1, 2]) / K[1, 1]
    return float(np.max(x * x + y * y))


def undistort(uv: np.ndarray, K: np.ndarray, D: Lens | np.ndarray | None) -> np.ndarray:
    """(N, 2) pixels -> (N, 2) normalised image coordinates (z = 1) of the pinhole camera they
    show, the lens (a Lens or a plumb_bob D) undone."""
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    lens = as_lens(D)
    if lens is not None:
        x, y = lens.undistort(x, y)
    return np.column_stack([x, y])


def seen_box(width: int, height: int, K: np.ndarray, D: Lens | np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """(low, high): the axis-aligned box of normalised image coordinates (z = 1) inside what
    a width x height image sees; the image itself without distortion. A lens bends the image's
    border in those coordinates (outwards between the corners for a barrel lens, inwards for a
    pincushion one), so each side of the box is where that border side comes nearest the
    centre. Cached per camera: the camera node asks for every image."""
    x0, y0, x1, y1 = _seen_box(int(width), int(height),
                               tuple(np.asarray(K, dtype=np.float64).ravel()), as_lens(D))
    return np.array([x0, y0]), np.array([x1, y1])


@lru_cache(maxsize=16)
def _seen_box(width: int, height: int, k: tuple[float, ...], lens: Lens | None
              ) -> tuple[float, float, float, float]:
    K = np.asarray(k).reshape(3, 3)
    t = np.linspace(0.0, 1.0, BORDER_SAMPLES)
    one, zero = np.ones_like(t), np.zeros_like(t)
    sides = [np.column_stack(uv) for uv in ((zero, t * height), (one * width, t * height),
                                            (t * width, zero), (t * width, one * height))]
    left, right, top, bottom = (undistort(side, K, lens) for side in sides)
    return (float(left[:, 0].max()), float(top[:, 1].max()), float(right[:, 0].min()),
            float(bottom[:, 1].min()))


def distort(x: np.ndarray, y: np.ndarray, D: Lens | np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates (z = 1) of a pinhole camera -> where the lens (a Lens or a
    plumb_bob D) puts them."""
    lens = as_lens(D)
    return (x, y) if lens is None else lens.distort(x, y)


def _coefficients(lens: Lens | None) -> tuple[np.ndarray, str]:
    """(D with all the lens model's coefficients, the model); no lens: plumb_bob zeros."""
    if lens is None:
        return np.zeros(5), PLUMB_BOB
    return np.array(lens.coefficients), lens.model


def _problem(c: CameraCalibration) -> str | None:
    if c.width <= 0 or c.height <= 0:
        return f'image size {c.width}x{c.height} is not positive'
    K, T = np.asarray(c.K), np.asarray(c.T_camera_cloud)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return 'K must be a finite 3x3 matrix'
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f'K has focal lengths {K[0, 0]:g}, {K[1, 1]:g}; both must be > 0'
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return 'T_camera_cloud must be a finite 4x4 matrix'
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0 or \
            not np.allclose(T[3], [0, 0, 0, 1]):
        return 'T_camera_cloud is not a rigid transform (rotation part not orthonormal)'
    n = MODELS.get(c.distortion_model, (0, 0))[1]
    if not n:
        return f'distortion_model {c.distortion_model!r} is not one of {", ".join(MODELS)}'
    if np.asarray(c.D).shape != (n,) or not np.all(np.isfinite(c.D)):
        return f'D must hold {n} finite {c.distortion_model} coefficients'
    return None
