"""The detector's parameters, declared once for the node, `fhld replay` and config/*.yaml.

Each field's metadata 'doc' is its one description: the node's ParameterDescriptor
(`ros2 param describe lane_detector NAME`) reads it with fhld_ros.dataclass_dict.field_docs.
This module needs no rclpy: the pipeline and `fhld replay` use it too.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from fhld_ros.dataclass_dict import documented, field_problems, from_dict
from fhld_ros.errors import ConfigError
from fhld_ros.model.config import REFINE_STEPS, SIZE_PX, FhldConfig

P = TypeVar('P')

# Each field's range or choices sit beside its doc (dataclass_dict.documented). Upper bounds keep
# memory and time finite (size_px = 100000 asked numpy for 75 GiB); they sit far above any
# useful setting.


@dataclass(frozen=True)
class DetectorParams:
    """Every parameter of lane_detector; field metadata 'doc' is the ROS descriptor text."""

    points_topic: str = documented('points', 'input sensor_msgs/PointCloud2 topic',
                                   length='[1, inf)')
    odom_topic: str = documented(
        'odom', 'input nav_msgs/Odometry topic; without messages the node works per sweep',
        length='[1, inf)')
    lanes_topic: str = documented(
        'lanes', 'output MarkerArray topic; ego lane Paths go to <lanes_topic>/ego_left|right',
        length='[1, inf)')
    detector: str = documented(
        'fhld', "'fhld' (the learned model) or 'classical' (rule-based baseline)",
        choices=('fhld', 'classical'))
    checkpoint: str = documented(
        '', 'FHLD weights (.pt); empty = the shipped fhld_ros/checkpoints/fhld.pt')
    device: str = documented('cpu', "'cpu' or 'cuda' for the model", choices=('cpu', 'cuda'))
    model_threads: int = documented(
        0, 'CPU threads for the model; 0 = auto: one per core with ONNX Runtime, 1 with '
        'TorchScript (whose OpenMP threads stalled beside the executor)', range='[0, 1024]')
    model_runtime: str = documented(
        'auto', "how the model runs: 'auto' (ONNX Runtime on the CPU when installed, else "
        "TorchScript), 'onnxruntime' (CPU) or 'torchscript'",
        choices=('auto', 'onnxruntime', 'torchscript'))
    score_threshold: float = documented(
        0.7, 'minimum lane confidence to publish (0.7, chosen on validation roads: fewer '
        'false lanes on unmarked roads, the same F1 on marked ones; higher trades true lanes '
        'for fewer false ones)', range='[0, 1]')
    refine_heights: bool = documented(
        True, 'FHLD lane heights follow the measured road surface (robust fit of the '
        "raster's minimum heights); false keeps the model's own heights")
    local_refine_steps: int = documented(
        FhldConfig.local_refine_steps, 'FHLD anchor cells re-centred on the segment they found '
        'and classified again this many times (0 = on the global curves only)',
        range=REFINE_STEPS)
    evidence_reach_m: float = documented(
        1.5, 'FHLD lanes are cut where no return lies within this distance (m) in the window: '
        'no lanes over ground the sensor never saw (0.0 = off)', range='[0, 100]')
    min_paint_contrast: float = documented(
        1.3, 'FHLD lanes whose brightest returns are not this many times as bright as the road '
        'on each side of them (at their height), nor 1.25 x this against the road right beside '
        'them, are dropped: no lanes along bare curbs, seams or light strips (0.0 = off)',
        range='[0, 100]')
    size_px: int = documented(640, 'BEV window size in cells (square)', range=SIZE_PX)
    resolution_m: float = documented(0.04, 'BEV cell size in metres', range='(0, 10]')
    accumulate_sec: float = documented(
        1.0, 'sweeps younger than this (relative to the newest) are accumulated',
        range='[0, 60]')
    max_sweeps: int = documented(10, 'at most this many sweeps are accumulated (memory bound)',
                                 range='[1, 1000]')
    rate_hz: float = documented(
        10.0, 'detection rate; the timer runs on ROS time (use_sim_time for bags)',
        range='(0, 1000]')
    max_points: int = documented(
        1 << 20, 'clouds of more than this many points (height x width, read from the header '
        'before anything is allocated) are refused as bad clouds; 1048576 = 4 x a 128 x 2048 '
        'sensor', range=f'(0, {1 << 28}]')
    odom_wait_sec: float = documented(
        1.0, 'a sweep newer than the newest odometry waits for it until a message stamped '
        'this much later arrives (live: or this long passes without any message); then it is '
        'detected alone in the cloud frame, as are the next sweeps until odometry resumes',
        range='[0, 10]')
    odom_extrapolate_sec: float = documented(
        0.2, 'live only: a sweep whose odometry is later than odometry usually is (a pose lost '
        'in DDS) goes in with the motion of the newest poses continued, when it lies at most '
        'this far past the newest pose; 0 = it waits (odom_wait_sec)', range='[0, 0.5]')
    intensity_scale: float = documented(
        0.0, 'checkpoints with absolute intensity only: full scale of the intensity field; '
        '0 = infer per sweep (1, 255, 65535). Contrast-encoded weights need none',
        range='[0, 1e9]')
    input_reliability: str = documented(
        'auto', "points subscription reliability: 'auto' (reliable, switching to best effort "
        "while a best-effort publisher exists), 'reliable' or 'best_effort'",
        choices=('auto', 'reliable', 'best_effort'))
    lidar_to_base: tuple[float, ...] = documented(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 'static cloud frame -> odometry child frame '
        '[x, y, z, roll, pitch, yaw], used when the cloud frame differs from child_frame_id',
        length=6)

    def __post_init__(self) -> None:
        """ConfigError naming every value out of its declared range (all of them, one line)."""
        problems = field_problems(self)
        if self.model_runtime == 'onnxruntime' and self.device != 'cpu':
            problems.append("model_runtime 'onnxruntime' needs device 'cpu'")
        if problems:
            raise ConfigError('; '.join(problems))


def load_params_yaml(path: str | Path, node_name: str = 'lane_detector',
                     cls: type[P] = DetectorParams) -> P:
    """A `cls` (DetectorParams, CameraParams) from a ROS 2 parameter file
    (`<node>: ros__parameters: {...}`).

    The node's section, else the `/**` wildcard one; use_sim_time (a parameter of every node)
    is accepted and left to ROS.
    """
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'cannot read parameter file {path}: {exc}') from exc
    section: Any = (document.get(node_name, document.get('/**'))
                    if isinstance(document, dict) else None)
    if not isinstance(section, dict) or 'ros__parameters' not in section:
        raise ConfigError(f'parameter file {path} has no {node_name}: ros__parameters section')
    try:
        return from_dict(cls, section['ros__parameters'], ignore=('use_sim_time',))
    except (TypeError, ValueError) as exc:  # TypeError: a value of the wrong kind
        raise ConfigError(f'parameter file {path}: {exc}') from exc
