"""Test set-up shared by the suite: DDS confined to loopback for every ROS context.

The environment is set at import time, before any test creates an rclpy context, and child
processes inherit it; the random domain id keeps concurrent runs apart.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fhld_ros.ros.env import loopback_dds_env  # noqa: E402

os.environ.update(loopback_dds_env())


@pytest.fixture(scope='session')
def ros_env() -> dict[str, str]:
    """Environment for child processes that join this run's DDS domain on loopback."""
    return dict(os.environ)


@pytest.fixture
def rclpy_context():
    """An initialised rclpy context, shut down after the test."""
    import rclpy
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    context.try_shutdown()


@pytest.fixture
def one_torch_thread():
    """The 2 cores are shared: one torch thread is steadier than two fighting other work."""
    import torch
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
