"""FHLD model parts: curves, RoIAlign, anchors, cell targets, detector I/O."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from model_fixtures import small_config

from fhld_ros.bev import BevSpec
from fhld_ros.geometry import resample_to_count
from fhld_ros.model.anchors import inference_anchors, training_anchors
from fhld_ros.model.cell_targets import cell_targets
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.curve import AdaptiveAxisCurve, FixedAxisCurve
from fhld_ros.model.detector import Detections, FhldDetector, with_segment_ends
from fhld_ros.model.inference import (
    OnnxFeatures,
    OnnxGraph,
    TracedFeatures,
    TracedGraph,
    serving_features,
)
from fhld_ros.model.local_branch import LocalPrediction
from fhld_ros.model.roi_align import roi_align
from fhld_ros.model.targets import prepare_targets, to_metres, to_normalised
from fhld_ros.parameters import DetectorParams

CURVES = [AdaptiveAxisCurve(), FixedAxisCurve()]


pytestmark = pytest.mark.usefixtures('one_torch_thread')




def random_params(n: int, curve, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    raw = torch.rand(n, 12, generator=gen) * 2 - 1
    raw[:, [0, 1, 3, 4]] = raw[:, [0, 1, 3, 4]].abs()  # terminals in the window
    return curve.constrain(raw)


def straight_lane(y: float, x0: float = -12.0, x1: float = 12.0) -> np.ndarray:
    xs = np.linspace(x0, x1, 25)
    return np.stack([xs, np.full_like(xs, y), np.zeros_like(xs)], axis=1)


# --- curves -----------------------------------------------------------------------------------

@pytest.mark.parametrize('curve', CURVES, ids=['adaptive', 'fixed'])
def test_curve_boundary_conditions_are_exact(curve):
    params = random_params(64, curve)
    ends = curve.evaluate(params, torch.tensor([0.0, 1.0]).expand(64, -1))
    assert torch.equal(ends[:, 0], params[:, 0:3])   # f(0) = D = p_s, bit for bit
    assert torch.equal(ends[:, 1], params[:, 3:6])   # f(1) = p_e, bit for bit
    big_a, big_b, big_c, big_d = curve.coefficients(params.double())
    assert torch.equal(big_d, params[:, 0:3].double())
    torch.testing.assert_close(big_a + big_b + big_c + big_d, params[:, 3:6].double(),
                               rtol=0, atol=1e-12)
    t = torch.rand(64, 9, dtype=torch.float64)
    poly = (big_a[:, None] * t[..., None] ** 3 + big_b[:, None] * t[..., None] ** 2
            + big_c[:, None] * t[..., None] + big_d[:, None])
    torch.testing.assert_close(curve.evaluate(params.double(), t), poly)


@pytest.mark.parametrize('curve', CURVES, ids=['adaptive', 'fixed'])
def test_curve_points_project_back_to_their_parameter(curve):
    params = random_params(32, curve, seed=1)
    t = torch.linspace(0.05, 0.95, 7).expand(32, -1)
    t_back = curve.project(curve.evaluate(params, t), params[:, 0:3], params[:, 3:6])
    torch.testing.assert_close(t_back, t, atol=1e-4, rtol=0)


def test_fixed_axis_curve_is_a_function_of_x():
    curve = FixedAxisCurve()
    params = random_params(16, curve, seed=2)
    pts = curve.evaluate(params, torch.linspace(0, 1, 11).expand(16, -1))
    dx = torch.diff(pts[..., 0], dim=1)
    torch.testing.assert_close(dx, dx[:, :1].expand_as(dx), atol=1e-6, rtol=0)  # x linear in t


def test_curvature_of_a_circle_like_arc():
    # f(t) = p_s + t (p_e - p_s) + t (1 - t) a: a parabola whose vertex curvature is known.
    curve = AdaptiveAxisCurve()
    params = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0]])
    kappa = curve.curvature_xy(params, torch.tensor([[0.5, 0.0]]))
    # y = 0.2 t (1 - t), x = t: y'' = -0.4, y'(0.5) = 0 -> kappa 0.4; at t=0 y' = 0.2.
    torch.testing.assert_close(kappa[0, 0], torch.tensor(0.4))
    torch.testing.assert_close(kappa[0, 1], torch.tensor(0.4 / 1.04 ** 1.5))


# --- RoIAlign ---------------------------------------------------------------------------------

def test_roi_align_matches_bilinear_reference_on_linear_features():
    h, w = 20, 24
    v, u = torch.meshgrid((torch.arange(h) + 0.5) / h, (torch.arange(w) + 0.5) / w,
                          indexing='ij')
    feats = torch.stack([u, v, 2 * u - 3 * v + 1])[None].repeat(2, 1, 1, 1)
    feats[1] *= -1  # the second batch item differs, to catch routing to the wrong item
    centres = torch.tensor([[0.5, 0.5], [0.3, 0.6], [0.7, 0.35]])
    batch = torch.tensor([0, 1, 0])
    side, out = 0.25, 4
    pooled = roi_align(feats, centres, batch, side, out, sampling=2)
    assert pooled.shape == (3, 3, out, out)
    bins = ((torch.arange(out) + 0.5) / out - 0.5) * side
    for k in range(3):  # bilinear is exact on linear maps: each bin = value at its centre
        bu = centres[k, 0] + bins[None, :].expand(out, out)
        bv = centres[k, 1] + bins[:, None].expand(out, out)
        sign = -1 if batch[k] == 1 else 1
        expected = sign * torch.stack([bu, bv, 2 * bu - 3 * bv + 1])
        torch.testing.assert_close(pooled[k], expected, atol=1e-5, rtol=0)


def test_roi_align_equals_average_of_grid_sample_points():
    gen = torch.Generator().manual_seed(3)
    feats = torch.rand(1, 5, 16, 16, generator=gen)
    centre, side = torch.tensor([[0.41, 0.57]]), 0.2
    pooled = roi_align(feats, centre, torch.zeros(1, dtype=torch.long), side, 2, sampling=2)
    # bin (row 1, col 0): samples at offsets (-3/8, -1/8) side in u and (1/8, 3/8) side in v
    us = centre[0, 0] + torch.tensor([-0.375, -0.125]) * side
    vs = centre[0, 1] + torch.tensor([0.125, 0.375]) * side
    grid = torch.stack(torch.meshgrid(us, vs, indexing='xy'), -1)[None] * 2 - 1
    ref = F.grid_sample(feats, grid, align_corners=False).mean((2, 3))[0]
    torch.testing.assert_close(pooled[0, :, 1, 0], ref)


# --- coordinates and targets ------------------------------------------------------------------

def test_normalised_coordinates_follow_the_bev_raster_convention():
    spec = BevSpec(640, 0.04)
    xyz = np.array([[-12.8, -12.8, 0.5], [0.0, 0.0, -1.0], [3.3, -7.1, 0.2]])
    uvz = to_normalised(xyz, spec.length_m)
    np.testing.assert_allclose(uvz[:, :2] * spec.size_px, spec.world_to_pixel(xyz))
    np.testing.assert_allclose(uvz[:, 2], xyz[:, 2])  # z stays in metres
    np.testing.assert_allclose(to_metres(uvz, spec.length_m), xyz)


def test_targets_are_resampled_evenly_and_padded():
    cfg = small_config(gt_points=11)
    lane = np.array([[-10.0, 1.0, 0.0], [-10.0, 1.0, 0.0], [0.0, 1.0, 0.1], [10.0, 1.0, 0.2]])
    gt = prepare_targets([[lane, lane[:1]], []], cfg)   # one-point lane dropped
    assert gt.points.shape == (2, 1, 11, 3) and gt.mask.tolist() == [[True], [False]]
    steps = torch.diff(gt.points[0, 0, :, 0])
    torch.testing.assert_close(steps, torch.full_like(steps, 20 / 10 / cfg.window_m))
    assert resample_to_count(np.zeros((3, 3)), 5) is None


def test_cell_targets_find_the_segment_in_each_cell():
    cfg = small_config()
    gt = prepare_targets([[straight_lane(0.0), straight_lane(1.0)]], cfg)
    r = cfg.cell_norm
    centres = torch.tensor([[[0.5, 0.5], [0.5, 0.5 + 0.7 / cfg.window_m], [0.5, 0.8],
                             [0.5 + 11.7 / cfg.window_m, 0.5]]])
    anchors, _ = training_anchors(torch.zeros(1, 1, 12), [(torch.tensor([0]), torch.tensor([0]))],
                                  gt, cfg, AdaptiveAxisCurve())
    anchors.centres, anchors.z = centres, torch.zeros(1, 4)
    anchors.valid = torch.ones(1, 4, dtype=torch.bool)
    tgt = cell_targets(anchors, gt, cfg)
    # cell 0 is centred on lane y=0: full-width segment, heading along x
    assert tgt.label[0].tolist() == [True, True, False, True]
    torch.testing.assert_close(tgt.centre[0, 0], torch.tensor([0.5, 0.5]))
    torch.testing.assert_close(tgt.length[0, 0], torch.tensor(r))
    assert abs(float(tgt.heading[0, 0, 0])) == pytest.approx(1.0)
    # cell 1 holds both lanes (y=0 at 0.7 m, y=1 at 0.3 m from its centre): the closer wins
    torch.testing.assert_close(tgt.centre[0, 1, 1], torch.tensor(0.5 + 1.0 / cfg.window_m))
    # cell 3 holds the end of lane y=0 (x = 12 m): a shorter segment ending at the lane end
    end_u = 0.5 + 12.0 / cfg.window_m
    start_u = float(centres[0, 3, 0]) - r / 2
    assert float(tgt.length[0, 3]) == pytest.approx(end_u - start_u, abs=1e-6)


# --- anchors ----------------------------------------------------------------------------------

def test_training_anchors_follow_the_matched_curves():
    cfg = small_config(anchor_noise=False, negative_ratio=0.5)
    curve = AdaptiveAxisCurve()
    curves = random_params(12, curve, seed=4).reshape(2, 6, 12)
    gt = prepare_targets([[straight_lane(0.0)], [straight_lane(1.0), straight_lane(-2.0)]], cfg)
    matches = [(torch.tensor([3]), torch.tensor([0])),
               (torch.tensor([0, 5]), torch.tensor([0, 1]))]
    pos, neg = training_anchors(curves, matches, gt, cfg, curve)
    assert pos.centres.shape == (3, cfg.cells_per_lane, 2)
    assert neg.centres.shape == (3, cfg.cells_per_lane // 2, 2)
    assert pos.batch.tolist() == [0, 1, 1] and pos.query.tolist() == [3, 0, 5]
    t = (torch.arange(cfg.cells_per_lane) + 0.5) / cfg.cells_per_lane
    on_curve = curve.evaluate(curves[1, 5], t)
    torch.testing.assert_close(pos.centres[2], on_curve[:, :2].clamp(0, 1))
    torch.testing.assert_close(pos.z[2], on_curve[:, 2])
    dist = (neg.centres[:, :, None] - pos.centres[:, None]).norm(dim=-1).amin(-1)
    assert bool((dist <= 2.5 * cfg.cell_norm + 1e-6).all())  # around the positives...
    assert float(dist.mean()) > 0.5 * cfg.cell_norm              # ...but not on them

    noisy, _ = training_anchors(curves, matches, gt, small_config(noise_px=1.0), curve)
    shift = (noisy.centres - pos.centres).norm(dim=-1) * cfg.size_px
    assert 0 < float(shift.max()) <= 2 * 1.0 * 2 ** 0.5 + 1e-4  # noise clipped at 2 sigma

    on_gt, _ = training_anchors(curves, matches, gt, cfg, curve, on_gt=True)
    torch.testing.assert_close(on_gt.centres[0, :, 1], torch.full((cfg.cells_per_lane,), 0.5))


def test_inference_anchors_are_denser_on_curved_lanes():
    cfg = small_config(infer_max_cells=200)
    curve = AdaptiveAxisCurve()
    straight = torch.tensor([0.1, 0.5, 0, 0.9, 0.5, 0, 0, 0, 0, 0, 0, 0])
    bent = torch.tensor([0.1, 0.5, 0, 0.9, 0.5, 0, 0, 1.2, 0, 0, 0, 0])
    anchors = inference_anchors(torch.stack([straight, bent]), torch.zeros(2, dtype=torch.long),
                                torch.arange(2), cfg, curve)
    counts = anchors.valid.sum(1)
    straight_len = 0.8 * cfg.window_m
    expected = round(straight_len / (cfg.infer_spacing_px * cfg.resolution_m))
    assert int(counts[0]) == expected
    # the bent lane is ~1.5x longer but gets well over 1.5x the cells, most near its apex
    assert int(counts[1]) > 2 * int(counts[0])
    pts = anchors.centres[1, :int(counts[1])]
    gaps = (pts[1:] - pts[:-1]).norm(dim=-1)
    assert float(gaps[len(gaps) // 2]) < 0.5 * float(gaps[0])
    u = anchors.centres[0, :int(counts[0]), 0]
    assert bool((torch.diff(u) > 0).all())  # ordered along the lane


# --- detector ---------------------------------------------------------------------------------

def test_training_forward_returns_everything_the_criterion_needs():
    torch.manual_seed(0)
    cfg = small_config()
    model = FhldDetector(cfg).train()
    raster = torch.rand(2, 4, 128, 128)
    out = model(raster, targets=[[straight_lane(0.0), straight_lane(3.5)], []])
    assert out['logits'].shape == (2, 6, 2) and out['curves'].shape == (2, 6, 12)
    assert len(out['aux_logits']) == cfg.dec_layers - 1
    assert [len(p) for p, _ in out['matches']] == [2, 0]
    pos = out['local']['positive']
    assert pos.centre.shape == (2, cfg.cells_per_lane, 2) and pos.logits.requires_grad
    only_global = model(raster)
    assert 'local' not in only_global
    with pytest.raises(ValueError, match='raster must be'):
        model(torch.rand(1, 4, 64, 64))


def test_detect_returns_ordered_lanes_in_window_metres():
    torch.manual_seed(1)
    cfg = small_config(local_score_threshold=0.0)
    model = FhldDetector(cfg)
    dets = model.detect(torch.rand(2, 4, 128, 128), score_threshold=0.0, curve_points=7)
    assert len(dets) == 2 and all(isinstance(d, Detections) for d in dets)
    for det in dets:
        assert 1 <= len(det.lanes) == len(det.confidences) <= cfg.num_queries
        assert len(det.lanes) <= len(det.curves) <= cfg.num_queries
        assert np.all((det.confidences >= 0) & (det.confidences <= 1))
        for lane in det.lanes:
            assert lane.ndim == 2 and lane.shape[1] == 3 and len(lane) >= 2
            assert np.all(np.abs(lane[:, :2]) <= cfg.window_m / 2 + 1e-6)
        assert all(sampled.shape == (7, 3) for sampled in det.curves)
    assert model.training  # detect leaves the mode as it found it
    none = model.detect(torch.rand(1, 4, 128, 128), score_threshold=1.01)[0]
    assert none.lanes == [] and none.confidences.shape == (0,)


class _HeadSeeingLaneAt(torch.nn.Module):
    """A local head that sees one lane along v = lane_v: it accepts cells within a quarter cell
    of it and, from anywhere, points each cell's segment centre onto it."""

    def __init__(self, cfg: FhldConfig, lane_v: float) -> None:
        super().__init__()
        self.cfg, self.lane_v = cfg, lane_v

    def forward(self, local_map, anchors) -> LocalPrediction:
        c = anchors.centres
        near = (c[..., 1] - self.lane_v).abs() < 0.25 * self.cfg.cell_norm
        heading = torch.zeros_like(c)
        heading[..., 0] = 1.0
        return LocalPrediction(logits=torch.where(near, 5.0, -5.0),
                               centre=torch.stack([c[..., 0], torch.full_like(c[..., 0],
                                                                         self.lane_v)], -1),
                               length=torch.full_like(c[..., 0], self.cfg.cell_norm),
                               heading=heading, z=anchors.z)


def test_detect_recentres_cells_on_the_segments_they_find():
    cfg = small_config()
    model = FhldDetector(cfg).eval()
    model.local_head = _HeadSeeingLaneAt(cfg, lane_v=0.5)
    off = 0.5 + 0.6 * cfg.cell_norm  # the global curve runs 0.6 cells beside the lane
    curves = torch.zeros(cfg.dec_layers, 1, cfg.num_queries, 12)
    curves[:, 0, 0, :6] = torch.tensor([0.1, off, 0.0, 0.9, off, 0.0])
    logits = torch.tensor([10.0, 0.0]).repeat(cfg.dec_layers, 1, cfg.num_queries, 1)
    logits[:, 0, 0] = torch.tensor([0.0, 10.0])  # query 0 is the only lane
    features = (logits, curves, torch.zeros(1, cfg.local_channels, 16, 16))
    raster = torch.zeros(1, 4, cfg.size_px, cfg.size_px)

    # cells left on the curve are all rejected; the global curve alone remains
    found = model.detect(raster, features=features, refine_heights=False, curve_points=5,
                         refine_steps=0)[0]
    assert found.lanes == [] and len(found.curves) == 1
    assert cfg.local_refine_steps == 2  # the default: re-centred cells find the lane
    lanes = model.detect(raster, features=features, refine_heights=False)[0].lanes
    assert len(lanes) == 1 and len(lanes[0]) >= 4
    np.testing.assert_allclose(lanes[0][:, 1], 0.0, atol=1e-5)  # v = 0.5 is y = 0 m
    with pytest.raises(ValueError, match='local_refine_steps'):
        FhldDetector(small_config(local_refine_steps=-1))


@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_lane_ends_reach_the_outer_ends_of_the_end_segments(sign):
    # cells along u at 0.2 .. 0.8, segments 0.1 long: the lane runs from 0.15 to 0.85
    centres = np.stack([np.linspace(0.2, 0.8, 4), np.full(4, 0.5), np.arange(4.0)], -1)
    reach = np.tile([[sign * 0.05, 0.0]], (4, 1))  # a heading's sign is arbitrary
    lane = with_segment_ends(centres, reach)
    assert lane.shape == (6, 3)
    np.testing.assert_allclose(lane[1:-1], centres)
    np.testing.assert_allclose(lane[[0, -1]], [[0.15, 0.5, 0.0], [0.85, 0.5, 3.0]])
    # ends beyond the window stop at its border
    edge = with_segment_ends(centres * [1.2, 1, 1] - [0.1, 0, 0], reach * 3)
    assert edge[:, :2].min() >= 0.0 and edge[:, :2].max() <= 1.0


def test_default_model_size_and_input_spec():
    cfg = FhldConfig()
    assert (cfg.size_px, cfg.resolution_m, cfg.widths, cfg.num_queries) == (640, 0.04,
                                                                            (16, 32, 64, 128), 15)
    model = FhldDetector(cfg)
    megabytes = sum(p.numel() * 4 for p in model.state_dict().values()) / 2 ** 20
    assert megabytes < 20
    with torch.inference_mode():
        out = model.eval()(torch.zeros(1, 4, 640, 640))
    assert out['curves'].shape == (1, 15, 12)


@pytest.mark.parametrize('runner', [TracedFeatures, OnnxFeatures])
def test_serving_features_match_eager_and_give_the_same_lanes(runner):
    torch.manual_seed(2)
    model = FhldDetector(small_config(local_score_threshold=0.0)).eval()
    raster = torch.rand(1, 4, 128, 128)
    served = runner(model)
    with torch.no_grad():
        for eager, graph in zip(model.features(raster), served(raster)):
            torch.testing.assert_close(graph, eager, rtol=1e-4, atol=1e-5)
    assert served.graph is not None and served.shape == (1, 4, 128, 128)
    eager_det = model.detect(raster, score_threshold=0.0)[0]
    graph_det = model.detect(raster, score_threshold=0.0, features=served(raster))[0]
    assert len(eager_det.lanes) == len(graph_det.lanes) >= 1
    for a, b in zip(eager_det.lanes, graph_det.lanes):
        np.testing.assert_allclose(a, b, atol=1e-4)
    other = torch.rand(2, 4, 128, 128)  # another shape: eager, same result
    torch.testing.assert_close(served(other)[2], model.features(other)[2])


def test_serving_runtime_choice():
    model = FhldDetector(small_config()).eval()
    assert isinstance(serving_features(model), OnnxGraph)  # onnxruntime is a dependency
    assert isinstance(serving_features(model, runtime='torchscript'), TracedGraph)
    assert isinstance(serving_features(model, device='cuda'), TracedGraph)
    with pytest.raises(ValueError, match='model_runtime'):
        DetectorParams(model_runtime='tensorrt')
    with pytest.raises(ValueError, match="needs device 'cpu'"):
        DetectorParams(model_runtime='onnxruntime', device='cuda')
