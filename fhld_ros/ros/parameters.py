"""The detector's parameters, declared once for the node, `fhld replay` and config/*.yaml.

Each field's metadata 'doc' is its one description: the node's ParameterDescriptor
(`ros2 param describe lane_detector NAME`) reads it with fhld_ros.dataclass_dict.field_docs.
This module needs no rclpy: the pipeline and `fhld replay` use it too.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from fhld_ros.dataclass_dict import documented, from_dict
from fhld_ros.errors import CliError
from fhld_ros.model.config import FhldConfig


@dataclass(frozen=True)
class DetectorParams:
    """Every parameter of lane_detector; field metadata 'doc' is the ROS descriptor text."""

    points_topic: str = documented('points', 'input sensor_msgs/PointCloud2 topic')
    odom_topic: str = documented(
        'odom', 'input nav_msgs/Odometry topic; without messages the node works per sweep')
    lanes_topic: str = documented(
        'lanes', 'output MarkerArray topic; ego lane Paths go to <lanes_topic>/ego_left|right')
    detector: str = documented(
        'fhld', "'fhld' (the learned model) or 'classical' (rule-based baseline)")
    checkpoint: str = documented(
        '', 'FHLD weights (.pt); empty = the shipped fhld_ros/checkpoints/fhld.pt')
    device: str = documented('cpu', "'cpu' or 'cuda' for the model")
    model_threads: int = documented(
        0, 'CPU threads for the model; 0 = auto: one per core with ONNX Runtime, 1 with '
        'TorchScript (whose OpenMP threads stalled beside the executor)')
    model_runtime: str = documented(
        'auto', "how the model runs: 'auto' (ONNX Runtime on the CPU when installed, else "
        "TorchScript), 'onnxruntime' (CPU) or 'torchscript'")
    score_threshold: float = documented(0.5, 'minimum lane confidence to publish')
    refine_heights: bool = documented(
        True, 'FHLD lane heights follow the measured road surface (robust fit of the '
        "raster's minimum heights); false keeps the model's own heights")
    local_refine_steps: int = documented(
        FhldConfig.local_refine_steps, 'FHLD anchor cells re-centred on the segment they found '
        'and classified again this many times (0 = on the global curves only)')
    evidence_reach_m: float = documented(
        1.5, 'FHLD lanes are cut where no return lies within this distance (m) in the window: '
        'no lanes over ground the sensor never saw (0 = off)')
    size_px: int = documented(640, 'BEV window size in cells (square)')
    resolution_m: float = documented(0.04, 'BEV cell size in metres')
    accumulate_sec: float = documented(
        1.0, 'sweeps younger than this (relative to the newest) are accumulated')
    max_sweeps: int = documented(10, 'at most this many sweeps are accumulated (memory bound)')
    rate_hz: float = documented(
        10.0, 'detection rate; the timer runs on ROS time (use_sim_time for bags)')
    max_points: int = documented(
        1 << 20, 'clouds of more than this many points (height x width, read from the header '
        'before anything is allocated) are refused as bad clouds; 1048576 = 4 x a 128 x 2048 '
        'sensor')
    odom_wait_sec: float = documented(
        1.0, 'a sweep newer than the newest odometry waits for it until a message stamped '
        'this much later arrives (live: or this long passes without any message); then it is '
        'detected alone in the cloud frame, as are the next sweeps until odometry resumes')
    intensity_scale: float = documented(
        0.0, 'full scale of the intensity field; 0 = infer per sweep (1, 255, 65535)')
    input_reliability: str = documented(
        'auto', "points subscription reliability: 'auto' (reliable, switching to best effort "
        "while a best-effort publisher exists), 'reliable' or 'best_effort'")
    lidar_to_base: tuple[float, ...] = documented(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 'static cloud frame -> odometry child frame '
        '[x, y, z, roll, pitch, yaw], used when the cloud frame differs from child_frame_id')

    def __post_init__(self) -> None:
        problems = []
        if self.detector not in ('fhld', 'classical'):
            problems.append(f"detector must be 'fhld' or 'classical', not {self.detector!r}")
        if self.device not in ('cpu', 'cuda'):
            problems.append(f"device must be 'cpu' or 'cuda', not {self.device!r}")
        if self.model_runtime not in ('auto', 'onnxruntime', 'torchscript'):
            problems.append("model_runtime must be 'auto', 'onnxruntime' or 'torchscript'")
        if self.model_runtime == 'onnxruntime' and self.device != 'cpu':
            problems.append("model_runtime 'onnxruntime' needs device 'cpu'")
        if self.input_reliability not in ('auto', 'reliable', 'best_effort'):
            problems.append("input_reliability must be 'auto', 'reliable' or 'best_effort'")
        if not isinstance(self.refine_heights, bool):
            problems.append('refine_heights must be true or false')
        steps = self.local_refine_steps
        if isinstance(steps, bool) or not (isinstance(steps, int) and steps >= 0):
            problems.append('local_refine_steps must be an integer >= 0')
        if len(self.lidar_to_base) != 6:
            problems.append('lidar_to_base must be [x, y, z, roll, pitch, yaw]')
        points = self.max_points
        if isinstance(points, bool) or not (isinstance(points, int) and points > 0):
            problems.append('max_points must be an integer > 0')
        if not 0 <= self.odom_wait_sec <= 10:
            problems.append('odom_wait_sec must be within 0..10')
        if not self.evidence_reach_m >= 0:
            problems.append('evidence_reach_m must be >= 0')
        if not (self.rate_hz > 0 and self.accumulate_sec >= 0 and self.max_sweeps >= 1
                and self.size_px >= 32 and self.resolution_m > 0):
            problems.append('rate_hz, resolution_m > 0, accumulate_sec >= 0, max_sweeps >= 1 '
                            'and size_px >= 32 are required')
        if problems:
            raise ValueError('; '.join(problems))


def load_params_yaml(path: str | Path, node_name: str = 'lane_detector') -> DetectorParams:
    """DetectorParams from a ROS 2 parameter file (`<node>: ros__parameters: {...}`).

    The node's section, else the `/**` wildcard one; use_sim_time (a parameter of every node)
    is accepted and left to ROS.
    """
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CliError(f'cannot read parameter file {path}: {exc}') from exc
    section: Any = (document.get(node_name, document.get('/**'))
                    if isinstance(document, dict) else None)
    if not isinstance(section, dict) or 'ros__parameters' not in section:
        raise CliError(f'parameter file {path} has no {node_name}: ros__parameters section')
    try:
        return from_dict(DetectorParams, section['ros__parameters'], ignore=('use_sim_time',))
    except (TypeError, ValueError) as exc:  # TypeError: a value of the wrong kind
        raise CliError(f'parameter file {path}: {exc}') from exc
