"""Detector back-ends behind one call: BevWindow -> (lanes in window frame, confidences).

The FHLD model is loaded here and nowhere else (checkpoint default, threads, device, errors as
ConfigError), for the node, `fhld replay`, `fhld demo` and `fhld testset`.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np
import torch

from fhld_ros.classical import ClassicalLaneDetector
from fhld_ros.errors import ConfigError
from fhld_ros.evidence import keep_observed, keep_painted
from fhld_ros.model.checkpoint import DEFAULT_CHECKPOINT, CheckpointError, load_checkpoint
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.detector import Detections, FhldDetector
from fhld_ros.model.heights import refine_lane_heights
from fhld_ros.model.inference import serving_features
from fhld_ros.parameters import DetectorParams
from fhld_ros.rolling_grid import BevWindow

Detector = Callable[[BevWindow], tuple[list[np.ndarray], np.ndarray]]
T = TypeVar('T')
# the FHLD readings of one detection that `fhld testset` scores side by side
FHLD_VARIANTS = ('fhld', 'fhld-model-z', 'fhld-global')
CURVE_POINTS = 200  # samples per global curve for 'fhld-global'


class Encoded(Generic[T]):
    """A detector with the intensity encoding (intensity.py) its windows must be made with,
    which a model's checkpoint records: LanePipeline and training_samples read it."""

    def __init__(self, detect: Callable[[BevWindow], T], intensity_encoding: str) -> None:
        self.detect = detect
        self.intensity_encoding = intensity_encoding
        # the last window's lanes its paint check dropped (none without one): LanePipeline
        # counts them for the diagnostics
        self.lanes_unpainted = 0

    def __call__(self, window: BevWindow) -> T:
        return self.detect(window)


def classical_detector() -> Detector:
    """The rule-based baseline on the accumulated window points."""
    baseline = ClassicalLaneDetector()
    return lambda window: baseline.detect(window.points_window, window.intensity)


def load_fhld_model(params: DetectorParams) -> FhldDetector:
    """The FHLD model from params.checkpoint on params.device, in eval mode."""
    # torch runs the post-processing (and TorchScript): small ops, fastest on one thread here
    torch.set_num_threads(params.model_threads if params.model_threads > 0 else 1)
    if params.device == 'cuda' and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was asked for but torch sees no CUDA device")
    expect = FhldConfig(size_px=params.size_px, resolution_m=params.resolution_m)
    try:
        loaded = load_checkpoint(params.checkpoint or DEFAULT_CHECKPOINT, expect=expect,
                                 map_location=params.device)
    except CheckpointError as exc:
        raise ConfigError(str(exc)) from exc
    return loaded.model.to(params.device).eval()


def fhld_detections(params: DetectorParams, eager: bool = False,
                    curve_points: int = 0) -> Encoded[Detections]:
    """BevWindow -> the model's Detections (lanes, confidences, curve_points-sampled curves).

    The backbone runs as the node serves it (serving_features: ONNX Runtime or TorchScript,
    params.model_runtime) unless eager, which runs the torch module itself: the two agree to
    float rounding only, and the published test-set table is the eager model's.
    """
    model = load_fhld_model(params)
    features = None
    if not eager:
        try:
            features = serving_features(model, params.device, params.model_runtime,
                                        params.model_threads)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        cfg = model.cfg  # build the graph now, not on the first sweep (export/trace takes ~2 s)
        features(torch.zeros(1, cfg.in_channels, cfg.size_px, cfg.size_px, device=params.device))

    def detect(window: BevWindow) -> Detections:
        raster = torch.from_numpy(window.raster).unsqueeze(0).to(params.device)
        return model.detect(raster, score_threshold=params.score_threshold,
                            curve_points=curve_points, refine_heights=params.refine_heights,
                            refine_steps=params.local_refine_steps,
                            features=None if features is None else features(raster))[0]
    return Encoded(detect, model.cfg.intensity_encoding)


def fhld_detector(params: DetectorParams) -> Encoded[tuple[list[np.ndarray], np.ndarray]]:
    """The FHLD model from params.checkpoint (default: the shipped weights), as served; lanes
    keep only their parts near observed ground and only if paint shows (evidence.py)."""
    detections = fhld_detections(params)

    def detect(window: BevWindow) -> tuple[list[np.ndarray], np.ndarray]:
        found = detections(window)
        lanes, confidences, encoded.lanes_unpainted = evidence_checked(
            found.lanes, found.confidences, window, params)
        return lanes, confidences
    encoded = Encoded(detect, detections.intensity_encoding)
    return encoded


def evidence_checked(lanes: list[np.ndarray], confidences: np.ndarray, window: BevWindow,
                     params: DetectorParams) -> tuple[list[np.ndarray], np.ndarray, int]:
    """The lanes cut to observed ground (params.evidence_reach_m), then those without paint
    dropped (params.min_paint_contrast): evidence.py. Also how many the paint check dropped."""
    res = window.spec.resolution_m
    lanes, confidences = keep_observed(lanes, confidences, window.raster, res,
                                       params.evidence_reach_m)
    painted, confidences = keep_painted(lanes, confidences, window.raster, res,
                                        params.min_paint_contrast)
    return painted, confidences, len(lanes) - len(painted)


def with_evidence(lanes: list[np.ndarray], confidences: np.ndarray, window: BevWindow,
                  params: DetectorParams) -> tuple[list[np.ndarray], np.ndarray]:
    """evidence_checked's lanes and confidences."""
    return evidence_checked(lanes, confidences, window, params)[:2]


def fhld_variants(params: DetectorParams,
                  eager: bool = True) -> Encoded[dict[str, list[np.ndarray]]]:
    """BevWindow -> {FHLD_VARIANTS name: lanes}, all from ONE model.detect call.

    'fhld' the final lanes (heights refined from the measured surface), 'fhld-model-z' the
    same lanes with the local branch's own heights (both with fhld_detector's evidence
    checks, after the heights), 'fhld-global' the global curves alone.
    params.refine_heights is ignored: both kinds of heights are returned.
    """
    detections = fhld_detections(dataclasses.replace(params, refine_heights=False), eager=eager,
                                 curve_points=CURVE_POINTS)

    def observed(lanes: list[np.ndarray], window: BevWindow) -> list[np.ndarray]:
        return with_evidence(lanes, np.zeros(len(lanes)), window, params)[0]

    def detect(window: BevWindow) -> dict[str, list[np.ndarray]]:
        found = detections(window)
        refined = refine_lane_heights(found.lanes, window.raster, window.spec.resolution_m)
        return {'fhld': observed(refined, window), 'fhld-model-z': observed(found.lanes, window),
                'fhld-global': found.curves}
    return Encoded(detect, detections.intensity_encoding)


def make_detector(params: DetectorParams) -> Detector:
    return classical_detector() if params.detector == 'classical' else fhld_detector(params)
