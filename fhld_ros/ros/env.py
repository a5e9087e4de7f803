"""Environment that keeps ROS 2 / DDS traffic on this host (docs/design.md §7)."""
from __future__ import annotations

import os
import random
from pathlib import Path

# Both keep DDS on 127.0.0.1. 'project': 32 MB shared-memory segments, a whole cloud in one
# message (the lower latency). 'default': Fast DDS's own segment size and rmw's own reader and
# writer settings, as in a user's graph nobody tuned: a large cloud goes through the
# publisher's segment in 64 kB fragments, overrunning it (docs/design.md §7).
PROFILES = {'project': 'fastdds_loopback.xml', 'default': 'fastdds_loopback_default_segment.xml'}


def loopback_profile(dds: str = 'project') -> Path:
    """A Fast DDS loopback-only profile, from the source tree or the installed share dir."""
    source = Path(__file__).resolve().parents[2] / 'config' / PROFILES[dds]
    if source.exists():
        return source
    # only for an installed package: test/conftest.py imports this module first thing
    from ament_index_python.packages import get_package_share_directory
    return Path(get_package_share_directory('fhld_ros')) / 'config' / PROFILES[dds]


def loopback_dds_env(domain_id: int | None = None, base: dict | None = None,
                     dds: str = 'project') -> dict[str, str]:
    """A copy of `base` (default os.environ) whose DDS traffic stays on loopback, with the
    transport `dds` names (PROFILES).

    A random domain id keeps concurrent runs (tests, demos) from seeing each other.
    """
    env = dict(os.environ if base is None else base)
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(loopback_profile(dds))
    if dds == 'project':  # its history memory policy and publish mode too (memory returned
        env['RMW_FASTRTPS_USE_QOS_FROM_XML'] = '1'  # after bursts)
    else:
        env.pop('RMW_FASTRTPS_USE_QOS_FROM_XML', None)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    # ROS_LOCALHOST_ONLY is deprecated in Jazzy and, when set, makes rcl ignore the range above
    env.pop('ROS_LOCALHOST_ONLY', None)
    env['RMW_IMPLEMENTATION'] = env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['ROS_DOMAIN_ID'] = str(random.randint(1, 100) if domain_id is None else domain_id)
    return env
