"""FHLD losses and matching: KL, curve fitting, Hungarian matcher, criterion, overfitting."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from model_fixtures import small_config as shared_small_config

from fhld_ros.model.config import FhldConfig
from fhld_ros.model.curve import AdaptiveAxisCurve, FixedAxisCurve
from fhld_ros.model.detector import FhldDetector
from fhld_ros.model.losses import (
    FhldCriterion,
    curve_fit_loss,
    gaussian_kl,
    segment_covariance,
    symmetric_kl,
)
from fhld_ros.model.matcher import HungarianMatcher, terminal_l1
from fhld_ros.model.targets import prepare_targets

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def small_config(**overrides) -> FhldConfig:
    return shared_small_config(**{'lsm_warmup': 0, **overrides})


def curved_lanes(window_m: float) -> list[np.ndarray]:
    xs = np.linspace(-window_m / 2, window_m / 2, 60)
    return [np.stack([xs, y0 + 0.01 * xs ** 2, 0.02 * xs], 1) for y0 in (-3.5, 0.0, 3.5)]


def paint(lanes: list[np.ndarray], cfg: FhldConfig) -> torch.Tensor:
    """A raster with the lanes drawn into the intensity and density channels."""
    raster = torch.zeros(1, 4, cfg.size_px, cfg.size_px)
    cols = np.arange(cfg.size_px)
    for lane in lanes:
        px = (lane[:, :2] + cfg.window_m / 2) / cfg.resolution_m
        rows = np.clip(np.interp(cols + 0.5, px[:, 0], px[:, 1]).astype(int), 0, cfg.size_px - 1)
        raster[0, 0, rows, cols] = 1.0
        raster[0, 1, rows, cols] = 0.5
    return raster


def random_gaussians(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    mu = torch.randn(n, 2, generator=gen, dtype=torch.float64)
    heading = torch.nn.functional.normalize(torch.randn(n, 2, generator=gen,
                                                        dtype=torch.float64), dim=-1)
    length = 0.5 + torch.rand(n, generator=gen, dtype=torch.float64)
    return mu, segment_covariance(length, heading, 0.1)


# --- Gaussians and KL -------------------------------------------------------------------------

def test_kl_is_zero_for_identical_gaussians_and_symmetric():
    mu0, cov0 = random_gaussians(50, seed=0)
    mu1, cov1 = random_gaussians(50, seed=1)
    torch.testing.assert_close(symmetric_kl(mu0, cov0, mu0, cov0),
                               torch.zeros(50, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(symmetric_kl(mu0, cov0, mu1, cov1),
                               symmetric_kl(mu1, cov1, mu0, cov0))
    assert bool((symmetric_kl(mu0, cov0, mu1, cov1) > 0).all())
    one_way = gaussian_kl(mu0, cov0, mu1, cov1)
    assert not torch.allclose(one_way, gaussian_kl(mu1, cov1, mu0, cov0))  # KL alone is not


def test_kl_closed_forms():
    cov = torch.diag(torch.tensor([4.0, 0.25], dtype=torch.float64))
    shift = torch.tensor([1.0, 0.5], dtype=torch.float64)
    zero = torch.zeros(2, dtype=torch.float64)
    # equal covariances: KL = 0.5 * d^T Sigma^-1 d = 0.5 * (1/4 + 0.25/0.25) = 0.625
    assert float(gaussian_kl(zero, cov, shift, cov)) == pytest.approx(0.625)
    # equal means, scaled covariance s * Sigma: KL = 0.5 * (2/s - 2 + 2 ln s)
    s = 3.0
    assert float(gaussian_kl(zero, cov, zero, s * cov)) == pytest.approx(
        0.5 * (2 / s - 2 + 2 * math.log(s)))


def test_segment_covariance_axes():
    heading = torch.tensor([[math.cos(0.3), math.sin(0.3)]])
    cov = segment_covariance(torch.tensor([2.0]), heading, 0.1)[0]
    along = heading[0]
    across = torch.tensor([-along[1], along[0]])
    assert float(along @ cov @ along) == pytest.approx(1.0)      # (l / 2)^2
    assert float(across @ cov @ across) == pytest.approx(0.01)   # (2 w_l)^2 given as 0.1
    assert float(along @ cov @ across) == pytest.approx(0.0, abs=1e-7)
    # the bar Gaussian depends on the line, not on which way the segment points
    torch.testing.assert_close(segment_covariance(torch.tensor([2.0]), -heading, 0.1)[0], cov)


# --- curve fitting ----------------------------------------------------------------------------

@pytest.mark.parametrize('curve', [AdaptiveAxisCurve(), FixedAxisCurve()], ids=['adp', 'fixed'])
def test_curve_fit_loss_is_zero_on_the_curve_and_direction_free(curve):
    params = curve.constrain(torch.tensor([[0.1, 0.3, -1.8, 0.9, 0.6, -1.7,
                                            0.05, 0.1, 0.2, -0.02, 0.1, 0.0]]))
    lane = curve.evaluate(params, torch.linspace(0, 1, 40)[None])       # (1, 40, 3)
    zero = curve_fit_loss(curve, params, lane, z_scale=0.04)
    assert float(zero) == pytest.approx(0.0, abs=1e-6)
    assert float(curve_fit_loss(curve, params, lane.flip(1), z_scale=0.04)) == pytest.approx(
        0.0, abs=1e-6)
    shifted = lane + torch.tensor([0.0, 0.01, 0.0])
    assert float(curve_fit_loss(curve, params, shifted, z_scale=0.04)) == pytest.approx(
        0.01, rel=0.05)


def test_fixed_axis_cannot_fit_a_lateral_lane_the_adaptive_axis_can():
    v = torch.linspace(0.1, 0.9, 30)
    lane = torch.stack([0.5 + 0.05 * (v - 0.5) ** 2, v, torch.zeros_like(v)], -1)[None]
    fits = {}
    for name, curve in (('adaptive', AdaptiveAxisCurve()), ('fixed', FixedAxisCurve())):
        raw = torch.zeros(1, 12)
        raw[0, :6] = torch.tensor([0.3, 0.3, 0.0, 0.7, 0.7, 0.0])
        raw.requires_grad_(True)
        opt = torch.optim.Adam([raw], lr=0.01)
        sched = torch.optim.lr_scheduler.StepLR(opt, 150, 0.3)
        for _ in range(400):
            loss = curve_fit_loss(curve, curve.constrain(raw), lane, 0.04).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        fits[name] = loss.item() * 25.6  # mean point error in metres
    assert fits['adaptive'] < 0.03 and fits['fixed'] > 1.0, fits


# --- matcher ----------------------------------------------------------------------------------

def lane_terminals(points: list[list[float]]) -> torch.Tensor:
    return torch.tensor(points).reshape(-1, 2, 3)


def test_matcher_toy_case():
    gt_lanes = [np.array([[-10.0, -3.5, 0.0], [10.0, -3.5, 0.0]]),
                np.array([[-10.0, 3.5, 0.0], [10.0, 3.5, 0.0]])]
    cfg = FhldConfig(gt_points=5)
    gt = prepare_targets([gt_lanes], cfg)
    u0, u1, v_r, v_l = 0.5 - 10 / 25.6, 0.5 + 10 / 25.6, 0.5 - 3.5 / 25.6, 0.5 + 3.5 / 25.6
    curves = torch.zeros(1, 4, 12)
    curves[0, 0, :6] = torch.tensor([u1, v_l, 0, u0, v_l, 0])       # left lane, reversed
    curves[0, 1, :6] = torch.tensor([0.5, 0.5, 0, 0.6, 0.5, 0])       # far from both
    curves[0, 2, :6] = torch.tensor([u0, v_r + 0.01, 0, u1, v_r, 0])  # right lane, near
    curves[0, 3, :6] = torch.tensor([u0, v_r, 0, u1, v_r, 0])         # right lane, exact
    logits = torch.zeros(1, 4, 2)
    matcher = HungarianMatcher(class_weight=1.0, terminal_weight=1.0, z_scale=1 / 25.6)
    (pred, gt_idx), = matcher(logits, curves, gt)
    assert gt_idx.tolist() == [0, 1] and pred.tolist() == [3, 0]
    # a confident query wins over a slightly closer but unsure one
    logits[0, 2, 1] = 5.0
    (pred, _), = matcher(logits, curves, gt)
    assert pred.tolist() == [2, 0]
    # no GT lanes: nothing matched
    (pred, gt_idx), = matcher(logits, curves, prepare_targets([[]], cfg))
    assert pred.numel() == 0 and gt_idx.numel() == 0


def test_terminal_cost_ignores_lane_direction():
    a = lane_terminals([[0.1, 0.2, 0.0, 0.8, 0.3, 1.0]])
    b = lane_terminals([[0.8, 0.3, 1.0, 0.1, 0.2, 0.0]])
    assert float(terminal_l1(a, b, 0.04)) == 0.0
    c = lane_terminals([[0.1, 0.2, 0.0, 0.8, 0.3, 2.0]])
    assert float(terminal_l1(a, c, 0.04)) == pytest.approx(0.04)


# --- criterion --------------------------------------------------------------------------------

def run_criterion(cfg: FhldConfig, iteration: int, seed: int = 0) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    model = FhldDetector(cfg)
    lanes = curved_lanes(cfg.window_m)
    out = model(paint(lanes, cfg), targets=[lanes])
    return FhldCriterion(cfg)(out, [lanes], iteration)


def test_local_losses_start_after_the_warm_up():
    cfg = small_config(lsm_warmup=100)
    early, late = run_criterion(cfg, 99), run_criterion(cfg, 100)
    global_part = sum(v for k, v in early.items() if k.startswith(('loss_cls', 'loss_curve')))
    torch.testing.assert_close(early['loss'], global_part)
    torch.testing.assert_close(late['loss'], global_part + late['loss_lsm'])
    assert late['loss_lsm'].item() > 0
    expected_lsm = (late['loss_shape'] + 0.5 * late['loss_sm'] + late['loss_cell_cls']
                    + late['loss_z'])
    torch.testing.assert_close(late['loss_lsm'], expected_lsm)
    assert {'loss_cls_0', 'loss_curve_0'} <= set(late)  # aux loss on the first decoder layer


def test_ablation_switches_change_the_losses():
    base = run_criterion(small_config(), 0)
    point = run_criterion(small_config(shape_matching=False), 0)
    assert point['loss_shape'].item() != pytest.approx(base['loss_shape'].item())
    no_sm = run_criterion(small_config(smoothness_loss=False), 0)
    assert no_sm['loss_sm'].item() == 0.0 and base['loss_sm'].item() > 0
    for flags in (dict(adaptive_axis=False), dict(anchor_noise=False), dict(anchors_on_gt=True),
                  dict(aux_loss=False)):
        losses = run_criterion(small_config(**flags), 0)
        assert torch.isfinite(losses['loss'])
    assert 'loss_cls_0' not in run_criterion(small_config(aux_loss=False), 0)


def test_criterion_handles_windows_without_lanes():
    cfg = small_config()
    model = FhldDetector(cfg)
    out = model(torch.zeros(2, 4, 128, 128), targets=[[], []])
    losses = FhldCriterion(cfg)(out, [[], []], 10)
    assert torch.isfinite(losses['loss']) and losses['loss_curve'].item() == 0.0
    losses['loss'].backward()


@pytest.mark.slow
def test_overfitting_one_sample_drives_the_loss_down():
    torch.manual_seed(0)
    cfg = small_config()
    model = FhldDetector(cfg)
    lanes = curved_lanes(cfg.window_m)
    raster, criterion = paint(lanes, cfg), FhldCriterion(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    history = []
    for it in range(100):
        losses = criterion(model(raster, targets=[lanes]), [lanes], it)
        opt.zero_grad()
        losses['loss'].backward()
        opt.step()
        history.append({k: v.item() for k, v in losses.items()})
    first = np.mean([h['loss'] for h in history[:5]])
    last = np.mean([h['loss'] for h in history[-10:]])
    assert last < 0.35 * first, (first, last)
    assert np.mean([h['loss_curve'] for h in history[-10:]]) < 0.3 * history[0]['loss_curve']
    # the trained model finds the three lanes, in window metres, near the GT
    det = model.detect(raster, score_threshold=0.5)[0]
    assert len(det.lanes) == 3
    xs = np.linspace(-cfg.window_m / 2, cfg.window_m / 2, 2000)
    dense = np.concatenate([np.stack([xs, y0 + 0.01 * xs ** 2, 0.02 * xs], 1)
                            for y0 in (-3.5, 0.0, 3.5)])
    for lane in det.lanes:
        error = np.linalg.norm(lane[:, None] - dense[None], axis=-1).min(1)
        assert np.median(error) < 0.5  # metres; cells are 1.6 m, pixels 0.2 m
