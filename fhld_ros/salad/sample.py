"""One camera image with its 3D lanes: what SALAD trains and is scored on, whatever the source
(the simulator, `fhld autolabel` bags, ONCE-3DLanes or OpenLane files)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fhld_ros.camera.lens import Lens
from fhld_ros.salad.road_plane import RoadPlane


@dataclass
class CameraLaneSample:
    """image: (H, W, 3) uint8 RGB. intrinsics: (3, 3) K of that image (pixel (0, 0)'s centre at
    u = v = 0). lanes: (N, 3) float64 polylines in the camera optical frame (x right, y down, z
    forward, metres), each ordered near to far, only what the image shows. name: where it came
    from (a file, a seed), for messages. road: the road under the camera where its mount is
    known (the simulator's), for depth up to road.until_m. distortion: the image's lens (a
    Lens, or plumb_bob's k1 k2 p1 p2 [k3]) where it has one (the warp removes it)."""

    image: np.ndarray
    intrinsics: np.ndarray
    lanes: list[np.ndarray] = field(default_factory=list)
    name: str = ''
    road: RoadPlane | None = None
    distortion: Lens | np.ndarray | None = None

    def __post_init__(self) -> None:
        image = np.asarray(self.image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f'{self.name or "sample"}: image must be (H, W, 3) uint8, got '
                             f'{image.shape} {image.dtype}')
        k = np.asarray(self.intrinsics, dtype=np.float64)
        if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f'{self.name or "sample"}: intrinsics must be a finite 3x3 K with '
                             f'positive focal lengths, got {k.tolist()}')
        self.image, self.intrinsics = image, k
        self.lanes = [np.asarray(lane, dtype=np.float64).reshape(-1, 3) for lane in self.lanes]

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]
