"""SaladDetector: one camera image and its intrinsics in, 3D lanes in the optical frame out
(resample to the virtual camera, the network, decode). The network runs as the LiDAR model's
backbone does (model/inference.py: ONNX Runtime on the CPU, 13.5 against 25.5 ms in eager torch
on one thread of the 2-core development machine, docs/performance.md)."""
from __future__ import annotations

import os
import time

import numpy as np
import torch

from fhld_ros.errors import ConfigError
from fhld_ros.model.inference import serving_graph
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, load_salad
from fhld_ros.salad.decode import decode


class SaladDetector:
    """runtime: 'auto' (ONNX Runtime when installed, else TorchScript), 'onnxruntime' or
    'torchscript'; threads: the network's CPU threads (0: the runtime's default)."""

    def __init__(self, checkpoint: str | os.PathLike = DEFAULT_SALAD_CHECKPOINT,
                 threads: int = 0, runtime: str = 'auto') -> None:
        if threads:
            torch.set_num_threads(threads)
        self.model, self.info = load_salad(checkpoint)
        self.cfg = self.model.cfg
        try:
            self.network = serving_graph(self.model, 'cpu', runtime, threads)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        camera = self.cfg.camera  # the graph is built now, not on the first image (~1 s)
        self.network(torch.zeros(1, 3, camera.height, camera.width, dtype=torch.uint8))
        self.timings_ms: dict[str, float] = {}

    @torch.inference_mode()
    def maps(self, image: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The network's maps of one image: lane probability (h, w) and spatial (3, h, w)."""
        start = time.perf_counter()
        warped = self.cfg.camera.warp(np.asarray(image), np.asarray(intrinsics))
        x = torch.from_numpy(warped).permute(2, 0, 1)[None]
        warp_done = time.perf_counter()
        seg, spatial = self.network(x)
        self.timings_ms = {'warp_ms': (warp_done - start) * 1e3,
                           'model_ms': (time.perf_counter() - warp_done) * 1e3}
        return torch.sigmoid(seg[0, 0]).numpy(), spatial[0].numpy()

    def __call__(self, image: np.ndarray, intrinsics: np.ndarray
                 ) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes ((N, 3) optical frame, metres, near to far) and their scores."""
        prob, spatial = self.maps(image, intrinsics)
        start = time.perf_counter()
        lanes, scores = decode(prob, spatial, self.cfg)
        self.timings_ms['decode_ms'] = (time.perf_counter() - start) * 1e3
        return lanes, scores
