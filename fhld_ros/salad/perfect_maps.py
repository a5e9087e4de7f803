"""SALAD with some of its maps replaced by the training targets of the image's own GT lanes:
what the decoding makes of a perfect segmentation, perfect offsets or perfect depth. Scoring
each combination (`fhld salad-eval --perfect depth`, ...) says which head costs the most F1
and how far the decoding alone lets F1 go (every head perfect).
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from fhld_ros.salad.detector import SaladDetector
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.targets import lane_targets

HEADS = ('seg', 'offsets', 'depth')
SURE = 0.99  # the probability a perfect segmentation gives lane cells (1 - SURE elsewhere)


class PerfectMaps:
    """Called as a SaladDetector on the samples that `over` yields, in that order (the lanes of
    the sample being scored are the targets)."""

    def __init__(self, detector: SaladDetector, heads: Iterable[str]) -> None:
        self.detector, self.heads = detector, set(heads)
        unknown = self.heads - set(HEADS)
        if unknown:
            raise ValueError(f'unknown heads {sorted(unknown)}: choose from {HEADS}')
        self._lanes: list[np.ndarray] = []

    def over(self, samples: Iterable[CameraLaneSample]) -> Iterator[CameraLaneSample]:
        for sample in samples:
            self._lanes = sample.lanes  # the optical frame: the virtual camera's too
            yield sample

    def __call__(self, image: np.ndarray, intrinsics: np.ndarray, road: RoadPlane | None = None,
                 distortion: np.ndarray | None = None) -> tuple[list[np.ndarray], np.ndarray]:
        prob, spatial = self.detector.maps(image, intrinsics, distortion)
        cfg = self.detector.cfg
        target = lane_targets(self._lanes, cfg.camera)
        lane = target.seg > 0
        spatial = spatial.copy()
        if 'seg' in self.heads:
            prob = np.where(lane, SURE, 1.0 - SURE)
        if 'offsets' in self.heads:  # targets exist at lane cells only
            spatial[:2] = np.where(lane, target.offsets, spatial[:2])
        if 'depth' in self.heads:
            spatial[2] = np.where(target.depth_mask, cfg.depth_residual(target.depth),
                                  spatial[2])
        return self.detector.decode(prob, spatial, road)
