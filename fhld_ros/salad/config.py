"""SaladConfig: what builds a SALAD model and decodes its output; saved in its checkpoint."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fhld_ros.dataclass_dict import check_fields, documented
from fhld_ros.errors import ConfigError
from fhld_ros.salad.virtual_camera import VirtualCamera

STRIDE = 4  # output cells per input pixel, each way (the paper's H/4 x W/4 maps)
# the training drives' cameras, optical centre above the road (m): by default, and those of
# the shipped salad_wide_mount.pt (the network's depth follows the heights it was trained on)
HEIGHT_RANGE_M = (1.2, 2.0)
WIDE_MOUNT_HEIGHTS_M = (1.2, 3.0)
# the fields only the loss reads: fine-tunes of one network may differ in them (salad-average)
LOSS_FIELDS = frozenset({'pos_weight', 'depth_weight', 'offset_weight', 'lane_depth_weight',
                         'lane_depth_beta'})
# the fields measured on given weights (calibrate.py): weights trained further or averaged need
# their own
CALIBRATION_FIELDS = frozenset({'depth_calibration_m', 'depth_calibration_log_gain'})


@dataclass(frozen=True)
class SaladConfig:
    camera: VirtualCamera = field(default_factory=VirtualCamera)
    widths: tuple[int, ...] = documented(
        (16, 32, 64, 96, 128), 'channels of the stem, then of the stages at strides 4 to 32',
        range='[4, 1024]', length=5, kind=int)
    decoder_dim: int = documented(48, 'channels of the fused stride-4 features',
                                  range='[4, 1024]')
    attention_layers: int = documented(
        1, 'self-attention layers over the stride-32 cells (global context)', range='[0, 8]')
    # depth z = row_shift[r] + row_scale[r] * dz per output row r (paper eq. 3): the mean and
    # spread of the training set's depths in that row, measured before training (targets.py)
    row_shift: tuple[float, ...] = documented((), 'depth shift per output row (m)',
                                              range='[0, inf)', kind=float)
    row_scale: tuple[float, ...] = documented((), 'depth scale per output row (m)',
                                              range='(0, inf)', kind=float)
    seg_threshold: float = documented(0.5, 'a cell is a lane cell above this probability',
                                      range='(0, 1)')
    score_threshold: float = documented(
        0.5, 'a decoded lane is kept when its mean cell probability reaches this',
        range='[0, 1]')
    max_depth_m: float = documented(60.0, 'lane points decoded farther away are dropped',
                                    range='(1, 1000]')
    pos_weight: float = documented(4.0, 'BCE weight of the (rare) lane cells',
                                   range='(0, 1000]')
    depth_weight: float = documented(1.0, 'lambda of paper eq. 6 for the depth residual',
                                     range='[0, 1000]')
    offset_weight: float = documented(1.0, 'lambda of paper eq. 6 for du, dv',
                                      range='[0, 1000]')
    # the dense depth term is mostly road and near rows, and its smooth L1 nearly flat at the
    # few per cent the lanes' depth is off by: this term weighs the lane cells alone, near L1
    lane_depth_weight: float = documented(
        0.0, "weight of a second depth term on the lane cells only (0: the paper's loss)",
        range='[0, 1000]')
    lane_depth_beta: float = documented(
        0.1, "that term's smooth L1 beta, in depth residual units", range='(0, 10]')
    # lanes in training end where the simulator's labels do (max_depth_m), so near it the
    # network's depth falls short of the truth by a few per cent (calibrate.py measures it on
    # held-out images): log(true / network depth) at network depths, interpolated between
    # them, held beyond them; none by default
    depth_calibration_m: tuple[float, ...] = documented(
        (), 'network depths (m, ascending) the calibration is measured at', range='(0, inf)',
        kind=float)
    depth_calibration_log_gain: tuple[float, ...] = documented(
        (), 'log(true / network depth) at those depths', range='[-1, 1]', kind=float)

    @property
    def grid(self) -> tuple[int, int]:
        """(width, height) of the output maps."""
        return self.camera.width // STRIDE, self.camera.height // STRIDE

    def network_depth(self, rows: np.ndarray, dz: np.ndarray) -> np.ndarray:
        """The network's depth (m) of cells in output rows `rows` with depth outputs dz."""
        return np.asarray(self.row_shift)[rows] + np.asarray(self.row_scale)[rows] * dz

    def calibrated(self, depth: np.ndarray) -> np.ndarray:
        """The network's depths (m) with the calibration applied."""
        if not self.depth_calibration_m:
            return depth
        return depth * np.exp(np.interp(depth, self.depth_calibration_m,
                                        self.depth_calibration_log_gain))

    def depth(self, rows: np.ndarray, dz: np.ndarray) -> np.ndarray:
        """Decoded depth (m): network_depth, calibrated."""
        return self.calibrated(self.network_depth(rows, dz))

    def depth_residual(self, depth: np.ndarray) -> np.ndarray:
        """dz of an (h, w) depth map (metres): the network's depth output that decodes to it."""
        depth = np.asarray(depth, dtype=np.float64)
        if self.depth_calibration_m:  # calibrated() inverted: it rises with depth (validate)
            grid = self._calibration_grid()
            beyond = depth * np.exp(-self.depth_calibration_log_gain[-1])
            depth = np.where(depth > grid[1][-1], beyond, np.interp(depth, grid[1], grid[0]))
        shift = np.asarray(self.row_shift)[:, None]
        return (depth - shift) / np.asarray(self.row_scale)[:, None]

    def _calibration_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(network depths from 0 to the last calibration depth, 1 cm apart; calibrated)."""
        network = np.linspace(0.0, self.depth_calibration_m[-1],
                              int(self.depth_calibration_m[-1] / 0.01) + 2)
        return network, self.calibrated(network)

    def validate(self, where: str = '') -> None:
        """ConfigError naming every field out of its declared range, and the rules between
        fields."""
        check_fields(self.camera, f'{where}.camera' if where else 'camera')
        check_fields(self, where)
        if self.camera.width % 32 or self.camera.height % 32:
            raise ConfigError(f'the camera must be a multiple of 32 px each way (the encoder '
                              f'halves it five times), got {self.camera.width} x '
                              f'{self.camera.height}')
        h = self.grid[1]
        if self.row_shift and (len(self.row_shift) != h or len(self.row_scale) != h):
            raise ConfigError(f'row_shift and row_scale need {h} values (one per output row '
                              f'of the {self.camera.height} px camera), got '
                              f'{len(self.row_shift)} and {len(self.row_scale)}')
        self._validate_calibration()

    def _validate_calibration(self) -> None:
        knots, gains = self.depth_calibration_m, self.depth_calibration_log_gain
        if len(knots) != len(gains):
            raise ConfigError(f'depth_calibration_m and depth_calibration_log_gain need as many '
                              f'values, got {len(knots)} and {len(gains)}')
        if knots and np.any(np.diff(knots) <= 0):
            raise ConfigError(f'depth_calibration_m must ascend, got {list(knots)}')
        if knots and np.any(np.diff(self._calibration_grid()[1]) <= 0):
            raise ConfigError('the depth calibration must keep farther depths farther: its '
                              f'gains {list(gains)} fall too fast between {list(knots)} m')


def uncalibrated(cfg: SaladConfig) -> SaladConfig:
    """cfg without a depth calibration: for weights that will differ from those it was measured
    on (trained further, averaged)."""
    return replace(cfg, **{name: () for name in CALIBRATION_FIELDS})
