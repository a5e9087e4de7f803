"""The detector's parameters, declared once for the node, `fhld replay` and config/*.yaml."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from fhld_ros.errors import CliError
from fhld_ros.model.config import FhldConfig


@dataclass(frozen=True)
class DetectorParams:
    """Every parameter of lane_detector; field metadata 'doc' is the ROS descriptor text."""

    points_topic: str = 'points'
    odom_topic: str = 'odom'
    lanes_topic: str = 'lanes'
    detector: str = 'fhld'
    checkpoint: str = ''
    device: str = 'cpu'
    model_threads: int = 0
    model_runtime: str = 'auto'
    score_threshold: float = 0.5
    refine_heights: bool = True
    local_refine_steps: int = FhldConfig.local_refine_steps
    size_px: int = 640
    resolution_m: float = 0.04
    accumulate_sec: float = 1.0
    max_sweeps: int = 10
    rate_hz: float = 10.0
    intensity_scale: float = 0.0
    input_reliability: str = 'auto'
    lidar_to_base: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

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
        if not (self.rate_hz > 0 and self.accumulate_sec >= 0 and self.max_sweeps >= 1
                and self.size_px >= 32 and self.resolution_m > 0):
            problems.append('rate_hz, resolution_m > 0, accumulate_sec >= 0, max_sweeps >= 1 '
                            'and size_px >= 32 are required')
        if problems:
            raise ValueError('; '.join(problems))


DESCRIPTIONS: dict[str, str] = {
    'points_topic': 'input sensor_msgs/PointCloud2 topic',
    'odom_topic': 'input nav_msgs/Odometry topic; without messages the node works per sweep',
    'lanes_topic': 'output MarkerArray topic; ego lane Paths go to <lanes_topic>/ego_left|right',
    'detector': "'fhld' (the learned model) or 'classical' (rule-based baseline)",
    'checkpoint': 'FHLD weights (.pt); empty = the shipped fhld_ros/checkpoints/fhld.pt',
    'device': "'cpu' or 'cuda' for the model",
    'model_threads': 'CPU threads for the model; 0 = auto: one per core with ONNX Runtime, 1 '
                     'with TorchScript (whose OpenMP threads stalled beside the executor)',
    'model_runtime': "how the model runs: 'auto' (ONNX Runtime on the CPU when installed, "
                     "else TorchScript), 'onnxruntime' (CPU) or 'torchscript'",
    'score_threshold': 'minimum lane confidence to publish',
    'refine_heights': 'FHLD lane heights follow the measured road surface (robust fit of the '
                      "raster's minimum heights); false keeps the model's own heights",
    'local_refine_steps': 'FHLD anchor cells re-centred on the segment they found and '
                          'classified again this many times (0 = on the global curves only)',
    'size_px': 'BEV window size in cells (square)',
    'resolution_m': 'BEV cell size in metres',
    'accumulate_sec': 'sweeps younger than this (relative to the newest) are accumulated',
    'max_sweeps': 'at most this many sweeps are accumulated (memory bound)',
    'rate_hz': 'detection rate; the timer runs on ROS time (use_sim_time for bags)',
    'intensity_scale': 'full scale of the intensity field; 0 = infer per sweep (1, 255, 65535)',
    'input_reliability': "points subscription reliability: 'auto' (reliable, switching to "
                         "best effort while a best-effort publisher exists), 'reliable' or "
                         "'best_effort'",
    'lidar_to_base': 'static cloud frame -> odometry child frame [x, y, z, roll, pitch, yaw], '
                     'used when the cloud frame differs from child_frame_id',
}


def load_params_yaml(path: str | Path, node_name: str = 'lane_detector') -> DetectorParams:
    """DetectorParams from a ROS 2 parameter file (`<node>: ros__parameters: {...}`)."""
    import yaml
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CliError(f'cannot read parameter file {path}: {exc}') from exc
    section: Any = document
    for key in (node_name, 'ros__parameters'):
        if not isinstance(section, dict) or key not in section:
            alt = '/**' if isinstance(section, dict) and '/**' in section else None
            if alt and key == node_name:
                section = section[alt]
                continue
            raise CliError(f'parameter file {path} has no {node_name}: ros__parameters section')
        section = section[key]
    known = {f.name for f in fields(DetectorParams)}
    unknown = sorted(set(section) - known - {'use_sim_time'})
    if unknown:
        raise CliError(f'parameter file {path}: unknown parameter(s) {", ".join(unknown)}')
    values = {k: (tuple(v) if isinstance(v, list) else v) for k, v in section.items()
              if k in known}
    try:
        return DetectorParams(**values)
    except (TypeError, ValueError) as exc:
        raise CliError(f'parameter file {path}: {exc}') from exc
