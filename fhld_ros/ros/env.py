"""Environment that keeps ROS 2 / DDS traffic on this host (docs/design.md §7)."""
from __future__ import annotations

import os
import random
from pathlib import Path

PROFILE_NAME = 'fastdds_loopback.xml'


def loopback_profile() -> Path:
    """The Fast DDS loopback-only profile, from the source tree or the installed share dir."""
    source = Path(__file__).resolve().parents[2] / 'config' / PROFILE_NAME
    if source.exists():
        return source
    # only for an installed package: test/conftest.py imports this module first thing
    from ament_index_python.packages import get_package_share_directory
    return Path(get_package_share_directory('fhld_ros')) / 'config' / PROFILE_NAME


def loopback_dds_env(domain_id: int | None = None, base: dict | None = None) -> dict[str, str]:
    """A copy of `base` (default os.environ) whose DDS traffic stays on loopback.

    A random domain id keeps concurrent runs (tests, demos) from seeing each other.
    """
    env = dict(os.environ if base is None else base)
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(loopback_profile())
    # its history memory policy and publish mode too (memory returned after bursts)
    env['RMW_FASTRTPS_USE_QOS_FROM_XML'] = '1'
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    # ROS_LOCALHOST_ONLY is deprecated in Jazzy and, when set, makes rcl ignore the range above
    env.pop('ROS_LOCALHOST_ONLY', None)
    env['RMW_IMPLEMENTATION'] = env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['ROS_DOMAIN_ID'] = str(random.randint(1, 100) if domain_id is None else domain_id)
    return env
