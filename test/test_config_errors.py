"""Every bad parameter or checkpoint: one line naming it on stderr, exit 2, no traceback.

lane_detector is started as `ros2 run fhld_ros lane_detector` starts it (the entry point
module, in its own process); `fhld` the same way. Each case once ended in a 30-line traceback
and exit 1, or started a node that used the value.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from model_fixtures import small_config

from fhld_ros.bagio import BagError, BagWriter
from fhld_ros.errors import ConfigError
from fhld_ros.importing.kitti import KittiError
from fhld_ros.importing.pcd import PcdError
from fhld_ros.model.checkpoint import CheckpointError, save_checkpoint
from fhld_ros.model.detector import FhldDetector
from msg_adapters.pointcloud2 import create_cloud

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SMALL = ('size_px:=128', 'resolution_m:=0.2')  # small_config's raster
SEC = 1_000_000_000
NO_GPU = pytest.mark.skipif(torch.cuda.is_available(), reason='this machine has a GPU')


@pytest.fixture(scope='module')
def bad_files(tmp_path_factory) -> Path:
    """A directory of unusable checkpoints, named by what is wrong with them."""
    root = tmp_path_factory.mktemp('checkpoints')
    good = save_checkpoint(root / 'good.pt', FhldDetector(small_config()), 'test')
    payload = torch.load(good, weights_only=True)
    first = next(iter(payload['state_dict']))
    payload['state_dict'][first] = torch.zeros(3, 3)
    torch.save(payload, root / 'wrong_shapes.pt')
    payload = torch.load(good, weights_only=True)
    payload['config']['d_model'] = 2 ** 20  # terabytes, if the model were built
    torch.save(payload, root / 'huge.pt')
    torch.save([1, 2, 3], root / 'not_fhld.pt')
    (root / 'random.pt').write_bytes(bytes(range(256)) * 16)
    (root / 'empty.pt').write_bytes(b'')
    data = good.read_bytes()
    (root / 'truncated.pt').write_bytes(data[:len(data) // 2])
    (root / 'folder.pt').mkdir()
    return root


# (ros parameters, what the one line must say); {root} is the bad_files directory
CASES = {
    'missing file': (['checkpoint:=/nonexistent.pt'], 'checkpoint not found: /nonexistent.pt'),
    'random bytes': (['checkpoint:={root}/random.pt'],
                     'checkpoint {root}/random.pt is corrupt or not a torch file'),
    'empty file': (['checkpoint:={root}/empty.pt'], '{root}/empty.pt is corrupt'),
    'truncated': (['checkpoint:={root}/truncated.pt', *SMALL], '{root}/truncated.pt is corrupt'),
    'wrong shapes': (['checkpoint:={root}/wrong_shapes.pt', *SMALL],
                     '{root}/wrong_shapes.pt does not fit the model built from its config'),
    'huge config': (['checkpoint:={root}/huge.pt', *SMALL],
                    '{root}/huge.pt has an unusable config: d_model must be an integer >= 1 '
                    'and <= 4096, not 1048576'),
    'not a checkpoint': (['checkpoint:={root}/not_fhld.pt'],
                         '{root}/not_fhld.pt is not an FHLD checkpoint'),
    'a directory': (['checkpoint:={root}/folder.pt'], '{root}/folder.pt is not a regular file'),
    '/dev/zero': (['checkpoint:=/dev/zero'], 'checkpoint /dev/zero is not a regular file'),
    'raster of another size': (['size_px:=33'], 'expects a 640 px raster at 0.04 m with 4 '
                               'channels, the input (parameters size_px, resolution_m) is 33 px'),
    'integer for a double': (['rate_hz:=0'],
                             'rate_hz must be a number with a decimal point (e.g. 10.0), not '
                             'integer 0'),
    'zero rate': (['rate_hz:=0.0'], 'rate_hz must be a number > 0 and <= 1000, not 0.0'),
    'string for an integer': (['size_px:=abc'], 'size_px must be an integer, not string abc'),
    'huge window': (['size_px:=100000', 'detector:=classical'],
                    'size_px must be an integer >= 32 and <= 4096, not 100000'),
    'negative threads': (['model_threads:=-1'],
                         'model_threads must be an integer >= 0 and <= 1024, not -1'),
    'unknown detector': (['detector:=deep'], "detector must be 'fhld' or 'classical', not 'deep'"),
    'unknown runtime': (['model_runtime:=tensorrt'], "model_runtime must be 'auto', "
                        "'onnxruntime' or 'torchscript', not 'tensorrt'"),
    'string for a bool': (['refine_heights:=maybe'],
                          'refine_heights must be true or false, not string maybe'),
    'short extrinsic': (['lidar_to_base:=[1.0,2.0]', 'detector:=classical'],
                        'lidar_to_base must be 6 finite numbers'),
    'bad topic name': (['points_topic:=bad!topic', 'detector:=classical'],
                       "points_topic 'bad!topic' is not a valid topic name: topic name must "
                       'not contain characters'),
    'score above 1': (['score_threshold:=1.5'],
                      'score_threshold must be a number >= 0 and <= 1, not 1.5'),
}
CUDA = (['device:=cuda'], "device 'cuda' was asked for but torch sees no CUDA device")


def _lane_detector(ros_env: dict[str, str], *ros_args: str) -> subprocess.CompletedProcess:
    """lane_detector with these --ros-args; killed (and the test failed) if it starts up."""
    return subprocess.run([sys.executable, '-m', 'fhld_ros.ros.lane_detector', '--ros-args',
                           *ros_args], env=ros_env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize('case', [*CASES, pytest.param('cuda without a GPU', marks=NO_GPU)])
def test_a_bad_parameter_or_checkpoint_is_one_line_and_exit_2(ros_env, bad_files, case):
    params, says = CASES.get(case, CUDA)
    # one model thread beside the suite; the case's own parameters come later and win
    args = [a for p in ['model_threads:=1', *params] for a in ('-p', p.format(root=bad_files))]
    result = _lane_detector(ros_env, *args)
    assert result.returncode == 2, result.stderr[-3000:]
    assert 'Traceback' not in result.stderr, result.stderr[-3000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith('lane_detector: error: '), lines[0]
    assert says.format(root=bad_files) in lines[0], lines[0]


def test_ros_arguments_rcl_cannot_parse_are_named(ros_env):
    result = _lane_detector(ros_env, '-p', 'lanes_topic:=')
    assert result.returncode == 2, result.stderr[-3000:]
    assert 'Traceback' not in result.stderr, result.stderr[-3000:]
    # rcl logs its own '[ERROR] [rcl]: Failed to parse global arguments' first
    assert result.stderr.strip().splitlines()[-1] == (
        "lane_detector: error: bad ROS arguments: Couldn't parse parameter override rule: "
        "'-p lanes_topic:='")


def test_fhld_replay_with_a_bad_checkpoint_is_one_line_and_exit_2(tmp_path, bad_files):
    bag = tmp_path / 'drive'
    with BagWriter(bag) as writer:
        cloud_type = writer.family.cls('sensor_msgs/msg/PointCloud2')
        points = np.zeros(10, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                     ('intensity', '<f4')])
        writer.write('/points', 'sensor_msgs/msg/PointCloud2', SEC, create_cloud(
            cloud_type, writer.family.header(SEC, 'lidar'), points))
    result = subprocess.run(
        [sys.executable, '-m', 'fhld_ros.cli', 'replay', str(bag), str(tmp_path / 'lanes'),
         '--checkpoint', str(bad_files / 'random.pt')], capture_output=True, text=True,
        timeout=120)
    assert result.returncode == 2, result.stderr[-3000:]
    assert result.stderr.strip().splitlines() == [
        f'fhld replay: error: checkpoint {bad_files}/random.pt is corrupt or not a torch file '
        '(UnpicklingError: invalid pickle data)'], result.stderr[-3000:]
    assert not (tmp_path / 'lanes').exists()


def test_one_error_hierarchy():
    assert issubclass(ConfigError, ValueError)
    assert issubclass(CheckpointError, ConfigError)
    assert all(issubclass(e, ConfigError) for e in (BagError, KittiError, PcdError))
