"""SaladDetector: one camera image and its intrinsics in, 3D lanes in the optical frame out
(resample to the virtual camera, the network, decode). The network runs as the LiDAR model's
backbone does (model/inference.py: ONNX Runtime on the CPU, 12.3 against 22.2 ms in eager torch
for one image on one thread of the 2-core development machine, docs/performance.md).

With flip_average the network also sees the image mirrored (one batch of two), and the two
maps are averaged: the virtual camera's principal point is on the vertical centre line, so
the mirror is exact, and it was trained on (augment.flip). On the validation images F1 at
tau_CD 0.3 went from 44.2 to 47.3: the depth of one pass scatters, and the mean of two
scatters less (docs/salad.md). It is off by default: on the 640 px view it takes the camera
node over the 50 ms target on a 2-core CPU, and the row profile (road_profile.py) took one
pass past what the mirror average scored before it."""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from fhld_ros.camera.lens import Lens
from fhld_ros.errors import ConfigError
from fhld_ros.model.inference import serving_graph
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, load_salad
from fhld_ros.salad.decode import decode
from fhld_ros.salad.double_lines import split_double_lines
from fhld_ros.salad.paint_evidence import MIN_CONTRAST, painted
from fhld_ros.salad.road_plane import RoadPlane
from fhld_ros.salad.virtual_camera import warm_sampler

MIRROR_SIGN = torch.tensor([-1.0, 1.0, 1.0]).view(3, 1, 1)  # du, dv, dz of a mirrored map


def add_decoding_arguments(parser: argparse.ArgumentParser) -> None:
    """The decoding's checks, for the commands that run the detector (decoding_options)."""
    parser.add_argument('--min-paint-contrast', type=float, default=MIN_CONTRAST, metavar='C',
                        help='drop the lanes whose pixels are not C times as bright as the '
                        'road on each side of them (0: off; default %(default)s, as the node)')
    parser.add_argument('--no-double-lines', dest='double_lines', action='store_false',
                        help='decode a double line as one lane (default: one per stripe, as '
                        'the node)')


def decoding_options(args: argparse.Namespace) -> dict:
    """SaladDetector's keywords from add_decoding_arguments' options."""
    return {'min_paint_contrast': args.min_paint_contrast, 'double_lines': args.double_lines}


class SaladDetector:
    """runtime: 'auto' (ONNX Runtime when installed, else TorchScript), 'onnxruntime' or
    'torchscript'; threads: the network's CPU threads (0: one per core with ONNX Runtime,
    whose workers do not spin, and one with TorchScript, whose OpenMP threads beside other work
    on 2 cores ran the network up to 40x slower); the few torch ops around the network run on
    one thread unless threads says more. flip_average: average the maps of the image and its
    mirror image (see the module doc); road_profile: pull the lane cells' depths towards the
    image's road profile (road_profile.py); min_paint_contrast: drop the lanes whose pixels are
    not this many times as bright as the road on each side of them (paint_evidence.py; 0 off);
    double_lines: split the lanes whose pixels show two stripes (double_lines.py).
    """

    def __init__(self, checkpoint: str | os.PathLike = DEFAULT_SALAD_CHECKPOINT,
                 threads: int = 0, runtime: str = 'auto', flip_average: bool = False,
                 road_profile: bool = True, min_paint_contrast: float = MIN_CONTRAST,
                 double_lines: bool = True) -> None:
        torch.set_num_threads(threads or 1)
        self.model, self.info = load_salad(checkpoint)
        self.cfg = self.model.cfg
        try:
            self.network = serving_graph(self.model, 'cpu', runtime, threads)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        self.flip_average, self.road_profile = flip_average, road_profile
        self.min_paint_contrast, self.double_lines = min_paint_contrast, double_lines
        self.warped: np.ndarray | None = None  # the last image, as the virtual camera sees it
        self.lanes_unpainted = 0  # the last image's decoded lanes the paint check dropped
        camera = self.cfg.camera  # the graph is built now, not on the first image (~1 s)
        # the graph is bound to the shape it is built for: that of batch()
        self.network(self.batch(np.zeros((camera.height, camera.width, 3), dtype=np.uint8)))
        warm_sampler()  # a distorted camera's first image does not wait for its compiling
        self.timings_ms: dict[str, float] = {}

    @torch.inference_mode()
    def maps(self, image: np.ndarray, intrinsics: np.ndarray,
             distortion: Lens | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The network's maps of one image (its lens distortion, if any, removed by the warp):
        lane probability (h, w) and spatial (3, h, w)."""
        start = time.perf_counter()
        self.warped = self.cfg.camera.warp(np.asarray(image), np.asarray(intrinsics),
                                           distortion)
        x = self.batch(self.warped)
        warp_done = time.perf_counter()
        seg, spatial = self.network(x)
        prob = torch.sigmoid(seg[:, 0])
        if self.flip_average:  # the mirror's maps mirrored back: du changes sign
            mirrored = spatial[1].flip(-1) * MIRROR_SIGN
            prob = 0.5 * (prob[0] + prob[1].flip(-1))
            spatial = 0.5 * (spatial[0] + mirrored)
        else:
            prob, spatial = prob[0], spatial[0]
        self.timings_ms = {'warp_ms': (warp_done - start) * 1e3,
                           'model_ms': (time.perf_counter() - warp_done) * 1e3}
        return prob.numpy(), spatial.numpy()

    def batch(self, warped: np.ndarray) -> torch.Tensor:
        """The network's input for one virtual-camera image (H, W, 3) uint8: (1, 3, H, W), or
        with flip_average (2, 3, H, W), the image and its mirror."""
        x = torch.from_numpy(warped).permute(2, 0, 1)[None]
        return torch.cat([x, x.flip(-1)]) if self.flip_average else x

    def __call__(self, image: np.ndarray, intrinsics: np.ndarray, road: RoadPlane | None = None,
                 distortion: Lens | np.ndarray | None = None
                 ) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes ((N, 3) optical frame, metres, near to far) and their scores; road: the road
        under the camera where its mount is known (road_plane.py); distortion: the image's lens
        (a Lens, or plumb_bob coefficients), if any."""
        prob, spatial = self.maps(image, intrinsics, distortion)
        start = time.perf_counter()
        lanes, scores = self.decode(prob, spatial, road)
        self.timings_ms['decode_ms'] = (time.perf_counter() - start) * 1e3
        return lanes, scores

    def decode(self, prob: np.ndarray, spatial: np.ndarray, road: RoadPlane | None = None
               ) -> tuple[list[np.ndarray], np.ndarray]:
        """The lanes of the last image's maps (or maps made from it), those without paint
        dropped (min_paint_contrast), double lines split (double_lines)."""
        lanes, scores = decode(prob, spatial, self.cfg, road, self.road_profile)
        keep = painted(lanes, self.warped, self.cfg.camera, self.min_paint_contrast)
        self.lanes_unpainted = int(np.count_nonzero(~keep))
        lanes = [lane for lane, kept in zip(lanes, keep) if kept]
        if not self.double_lines:
            return lanes, scores[keep]
        return split_double_lines(lanes, scores[keep], self.warped, self.cfg.camera)
