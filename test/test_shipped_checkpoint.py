"""The shipped FHLD weights find the lanes of held-out simulated windows (a regression test)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fhld_ros.data.cache import TEST_SEED_BASE, CacheSettings, scenario_for_seed
from fhld_ros.data.samples import training_samples
from fhld_ros.detectors import CURVE_POINTS, fhld_variants, with_evidence
from fhld_ros.evaluation import metrics
from fhld_ros.model.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint
from fhld_ros.model.config import FhldConfig
from fhld_ros.parameters import DetectorParams
from fhld_ros.sim.simulator import Simulator

# Held-out seeds (never trained on); thresholds sit a margin below what the shipped weights
# score on these windows (docs/accuracy.md) so a regression fails the test.
SEEDS = [TEST_SEED_BASE + k for k in (1, 5, 10, 14)]
MIN_F1_30 = 82.0  # shipped weights: 89.8 on these 4 windows (224-window test set: 96.0)
MIN_F1_10 = 72.0  # shipped weights: 80.2 (test set: 89.3)


@pytest.fixture(scope='module')
def windows():
    settings = CacheSettings(windows_per_seed=1)
    encoding = load_checkpoint(DEFAULT_CHECKPOINT).config.intensity_encoding
    samples = []
    for seed in SEEDS:
        sim = Simulator(seed, sweeps=settings.sweeps_per_seed, **scenario_for_seed(seed, settings))
        samples.extend(training_samples(sim, 1, keep_window=True, intensity_encoding=encoding))
    return samples


def test_shipped_checkpoint_loads_safely_with_its_provenance():
    loaded = load_checkpoint(DEFAULT_CHECKPOINT, expect=FhldConfig())
    assert DEFAULT_CHECKPOINT.stat().st_size <= 20 * 2 ** 20
    assert 'fhld train' in loaded.train_command
    assert loaded.code_version


@pytest.mark.slow  # simulating the four windows takes most of it
def test_shipped_checkpoint_detects_lanes(windows, one_torch_thread):
    model = load_checkpoint(DEFAULT_CHECKPOINT).model.eval()
    counts = metrics.PointCounts()
    for sample in windows:
        found = model.detect(torch.from_numpy(sample.raster).unsqueeze(0))[0]
        counts += metrics.point_counts(metrics.clip_lanes_to_square(found.lanes, 12.8),
                                       sample.lanes)
    scores = counts.scores()
    assert sum(len(s.lanes) for s in windows) > 0
    assert scores['F1@30'] >= MIN_F1_30, scores
    assert scores['F1@10'] >= MIN_F1_10, scores
    assert np.isfinite(list(scores.values())).all()


@pytest.mark.slow
def test_one_detection_gives_every_testset_variant(windows, one_torch_thread):
    """`fhld testset`'s FHLD rows: one eager detect() per window, read three ways."""
    model = load_checkpoint(DEFAULT_CHECKPOINT).model.eval()
    variants = fhld_variants(DetectorParams(model_threads=1))
    for sample in windows:
        found = variants(sample.window)
        raster = torch.from_numpy(sample.raster).unsqueeze(0)
        for name, refine in (('fhld', True), ('fhld-model-z', False)):
            det = model.detect(raster, refine_heights=refine)[0]
            lanes = with_evidence(det.lanes, det.confidences, sample.window,
                                  DetectorParams())[0]
            assert len(found[name]) == len(lanes)
            for got, want in zip(found[name], lanes):
                np.testing.assert_array_equal(got, want)
        # a curve per lane the node's score threshold keeps, before cutting (detect()'s own
        # threshold is lower)
        kept = np.count_nonzero(det.confidences >= DetectorParams().score_threshold)
        assert len(found['fhld-global']) >= kept
        assert all(curve.shape == (CURVE_POINTS, 3) for curve in found['fhld-global'])
    assert any(len(variants(sample.window)['fhld']) for sample in windows)
