"""SaladDetector: one camera image and its intrinsics in, 3D lanes in the optical frame out
(resample to the virtual camera, the network, decode)."""
from __future__ import annotations

import os
import time

import numpy as np
import torch

from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, load_salad
from fhld_ros.salad.decode import decode


class SaladDetector:
    def __init__(self, checkpoint: str | os.PathLike = DEFAULT_SALAD_CHECKPOINT,
                 threads: int = 0) -> None:
        if threads:
            torch.set_num_threads(threads)
        self.model, self.info = load_salad(checkpoint)
        self.cfg = self.model.cfg
        self.timings_ms: dict[str, float] = {}

    @torch.inference_mode()
    def __call__(self, image: np.ndarray, intrinsics: np.ndarray
                 ) -> tuple[list[np.ndarray], np.ndarray]:
        """Lanes ((N, 3) optical frame, metres, near to far) and their scores."""
        start = time.perf_counter()
        warped = self.cfg.camera.warp(np.asarray(image), np.asarray(intrinsics))
        x = torch.from_numpy(warped).permute(2, 0, 1)[None]
        warp_done = time.perf_counter()
        seg, spatial = self.model(x)
        net_done = time.perf_counter()
        lanes, scores = decode(torch.sigmoid(seg[0, 0]).numpy(), spatial[0].numpy(), self.cfg)
        self.timings_ms = {'warp_ms': (warp_done - start) * 1e3,
                           'model_ms': (net_done - warp_done) * 1e3,
                           'decode_ms': (time.perf_counter() - net_done) * 1e3}
        return lanes, scores
