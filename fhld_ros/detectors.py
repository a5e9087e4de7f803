"""Detector back-ends behind one call: BevWindow -> (lanes in window frame, confidences)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fhld_ros.errors import CliError
from fhld_ros.rolling_grid import BevWindow
from fhld_ros.ros.parameters import DetectorParams

Detector = Callable[[BevWindow], tuple[list[np.ndarray], np.ndarray]]


def classical_detector() -> Detector:
    """The rule-based baseline on the accumulated window points."""
    from fhld_ros.classical import ClassicalLaneDetector
    baseline = ClassicalLaneDetector()
    return lambda window: baseline.detect(window.points_window, window.intensity)


def fhld_detector(params: DetectorParams) -> Detector:
    """The FHLD model from params.checkpoint (default: the shipped weights)."""
    import torch

    from fhld_ros.model.checkpoint import DEFAULT_CHECKPOINT, CheckpointError, load_checkpoint
    from fhld_ros.model.config import FhldConfig
    from fhld_ros.model.inference import serving_features
    path = params.checkpoint or DEFAULT_CHECKPOINT
    # torch runs the post-processing (and TorchScript): small ops, fastest on one thread here
    torch.set_num_threads(params.model_threads if params.model_threads > 0 else 1)
    if params.device == 'cuda' and not torch.cuda.is_available():
        raise CliError("device 'cuda' was asked for but torch sees no CUDA device")
    expect = FhldConfig(size_px=params.size_px, resolution_m=params.resolution_m)
    try:
        loaded = load_checkpoint(path, expect=expect, map_location=params.device)
    except CheckpointError as exc:
        raise CliError(str(exc)) from exc
    model = loaded.model.to(params.device).eval()
    try:
        features = serving_features(model, params.device, params.model_runtime,
                                    params.model_threads)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    cfg = model.cfg  # build the graph now, not on the first sweep (export/trace takes ~2 s)
    features(torch.zeros(1, cfg.in_channels, cfg.size_px, cfg.size_px, device=params.device))

    def detect(window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]:
        raster = torch.from_numpy(window.raster).unsqueeze(0).to(params.device)
        found = model.detect(raster, score_threshold=params.score_threshold,
                             refine_heights=params.refine_heights,
                             refine_steps=params.local_refine_steps,
                             features=features(raster))[0]
        return found.lanes, found.confidences
    return detect


def make_detector(params: DetectorParams) -> Detector:
    return classical_detector() if params.detector == 'classical' else fhld_detector(params)
