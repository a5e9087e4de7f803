"""The far depth calibration: SaladConfig's gains in the decoding, their measurement
(`fhld salad-calibrate`), and weights trained further or averaged leaving it behind."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fhld_ros.cli import main
from fhld_ros.errors import ConfigError
from fhld_ros.salad.calibrate import BIN_M, MIN_CELLS, calibration, depth_ratios
from fhld_ros.salad.checkpoint import load_salad, save_salad
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.decode import decode, lane_points
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.targets import lane_targets, row_statistics

FAR = dict(depth_calibration_m=(30.0, 50.0), depth_calibration_log_gain=(0.0, 0.05))


def _lanes() -> list[np.ndarray]:
    z = np.linspace(3.0, 70.0, 1000)
    return [np.column_stack([np.full_like(z, x0), np.full_like(z, 1.5), z])
            for x0 in (-5.25, -1.75, 1.75, 5.25)]


def _config(targets, **calibration) -> SaladConfig:
    shift, scale = row_statistics(targets.depth[None], targets.depth_mask[None])
    return dataclasses.replace(SaladConfig(), row_shift=tuple(shift), row_scale=tuple(scale),
                               **calibration)


def test_the_decoding_multiplies_each_depth_by_its_gain_and_perfect_maps_invert_it():
    lanes = _lanes()
    targets = lane_targets(lanes, SaladConfig().camera)
    plain, calibrated = _config(targets), _config(targets, **FAR)
    calibrated.validate()
    dz = plain.depth_residual(targets.depth)  # the network's output for the true depths
    rows = np.arange(dz.shape[0])[:, None]
    net = plain.depth(rows, dz)
    gain = np.exp(np.interp(net, *FAR.values()))
    on = targets.depth_mask
    assert np.allclose(calibrated.depth(rows, dz)[on], (net * gain)[on])
    assert gain[on].max() == pytest.approx(np.exp(0.05)) and gain[on].min() == 1.0
    # depth_residual inverts the calibration: perfect maps still decode to the lanes
    assert np.allclose(calibrated.depth(rows, calibrated.depth_residual(targets.depth))[on],
                       targets.depth[on], atol=1e-3)
    spatial = np.concatenate([targets.offsets, dz[None]])
    points = lane_points(targets.seg * 0.9, spatial, calibrated, road_profile=False)
    # a cell keeps its ray: beyond 50 m of network depth its line lies 5 % further out
    line = np.array([-5.25, -1.75, 1.75, 5.25])
    full, none = points[:, 2] > 50.0 * np.exp(0.05), points[:, 2] < 30.0
    assert full.sum() >= 4 and none.sum() >= 20
    for subset, gain in ((full, np.exp(0.05)), (none, 1.0)):
        x = points[subset, 0]
        nearest = line[np.argmin(abs(x[:, None] / gain - line), axis=1)]
        assert np.allclose(x, nearest * gain, atol=0.03)
    decoded = decode(targets.seg * 0.9, spatial, calibrated)[0]
    assert len(decoded) == 4


@pytest.mark.parametrize('fields, message', [
    (dict(depth_calibration_m=(30.0,), depth_calibration_log_gain=(0.0, 0.1)), 'as many'),
    (dict(depth_calibration_m=(40.0, 30.0), depth_calibration_log_gain=(0.0, 0.1)), 'ascend'),
    (dict(depth_calibration_m=(30.0, 31.0), depth_calibration_log_gain=(0.5, -0.5)),
     'farther depths farther'),
    (dict(depth_calibration_m=(30.0,), depth_calibration_log_gain=(2.0,)), 'log_gain'),
])
def test_a_calibration_that_would_scramble_depths_is_refused(fields, message):
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(SaladConfig(), **fields).validate()


def test_the_calibration_is_the_median_per_bin_of_depth_with_enough_cells():
    rng = np.random.default_rng(0)
    network = rng.uniform(0.0, 60.0, 20000)
    truth = np.where(network > 45.0, 0.04, 0.0) + rng.normal(0.0, 0.02, network.size)
    knots, gains = calibration(network, truth, 60.0)
    assert len(knots) == int(60.0 / BIN_M)
    assert np.allclose(gains, np.where(np.array(knots) > 45.0, 0.04, 0.0), atol=0.005)
    # the first bin's cells, and one too few beyond 55 m
    few = np.concatenate([network[network < 5.0], np.full(MIN_CELLS - 1, 57.0)])
    assert len(calibration(few, np.zeros(few.size), 60.0)[0]) == 1
    with pytest.raises(ConfigError, match='too few lane cells'):
        calibration(np.full(10, 20.0), np.zeros(10), 60.0)


class _PerfectNetwork:
    """maps() as a network whose depth is the truth times `factor` at the lane cells."""

    def __init__(self, cfg: SaladConfig, factor: float) -> None:
        self.cfg, self.factor = cfg, factor

    def maps(self, image, intrinsics, distortion=None):
        targets = lane_targets(self.lanes, self.cfg.camera)
        dz = self.cfg.depth_residual(targets.depth * self.factor)
        return targets.seg * 0.9, np.concatenate([targets.offsets, dz[None]])


def test_the_measured_ratios_are_the_truth_over_the_network_at_lane_cells():
    lanes = _lanes()
    network = _PerfectNetwork(_config(lane_targets(lanes, SaladConfig().camera)), 0.95)
    network.lanes = lanes
    sample = CameraLaneSample(image=np.zeros((256, 640, 3), np.uint8), lanes=lanes,
                              intrinsics=SaladConfig().camera.intrinsics)
    depth, log_ratio = depth_ratios(network, [sample, sample])
    assert len(depth) > 100 and np.allclose(log_ratio, -np.log(0.95), atol=1e-6)


@pytest.mark.slow
def test_salad_calibrate_writes_a_calibrated_copy_and_never_overwrites(tmp_path, capsys):
    out = tmp_path / 'calibrated.pt'
    args = ['salad-calibrate', 'salad', str(out), '--drives', '2', '--frames', '1']
    assert main(args) == 0
    model, info = load_salad(out)
    shipped, shipped_info = load_salad('salad')
    assert len(model.cfg.depth_calibration_m) >= 1
    assert info['train_command'] == shipped_info['train_command']
    assert info['meta']['calibrated']['sources'] == ['validation drives']
    assert info['meta']['steps'] == shipped_info['meta']['steps']
    out.write_bytes(b'a user file')
    assert main(args) == 2
    assert 'exists' in capsys.readouterr().err and out.read_bytes() == b'a user file'
    assert main(['salad-calibrate', 'salad', str(tmp_path / 'x.pt'), '--drives', '0']) == 2
    assert 'nothing to calibrate on' in capsys.readouterr().err


def test_weights_averaged_leave_a_calibration_behind(tmp_path):
    model, _ = load_salad('salad')
    save_salad(tmp_path / 'a.pt', model, 'run a')
    model.cfg = dataclasses.replace(model.cfg, **FAR)
    save_salad(tmp_path / 'b.pt', model, 'run b, calibrated')
    out = tmp_path / 'mean.pt'
    assert main(['salad-average', str(out), str(tmp_path / 'a.pt'), str(tmp_path / 'b.pt')]) == 0
    assert load_salad(out)[0].cfg.depth_calibration_m == ()
