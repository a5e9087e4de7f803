"""`fhld bench`: stage timings as medians on the machine it runs on.

Each section is a function ``() -> dict[str, float]`` in bench_stages.py (bench_e2e.py for the
node end to end, bench_camera.py for SALAD, the camera detector, and its node), registered in
SECTIONS as 'module:function' and imported only when it runs.
``fhld bench --json`` merges all sections into one flat JSON object; ``fhld bench adapters``
runs one. ``--dds`` picks the DDS transports e2e and camera_live measure their node over
(default both, their keys named e2e_project_*, e2e_default_*, camera_live_project_*, ...).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform

from fhld_ros.errors import ConfigError

STAGES = 'fhld_ros.commands.bench_stages'
SECTIONS: dict[str, str] = {
    'adapters': f'{STAGES}:bench_decode',
    'bev': f'{STAGES}:bench_bev',
    'classical': f'{STAGES}:bench_classical',
    'metrics': f'{STAGES}:bench_metrics',
    'model': f'{STAGES}:bench_model',
    'simulator': f'{STAGES}:bench_simulator',
    'e2e': 'fhld_ros.commands.bench_e2e:bench_e2e',
    'camera': 'fhld_ros.commands.bench_camera:bench_camera',
    'camera_live': 'fhld_ros.commands.bench_camera:bench_camera_live',
}
# --dds -> the transports of fhld_ros.ros.env.PROFILES that e2e and camera_live run, in order
DDS_CHOICES: dict[str, tuple[str, ...]] = {
    'project': ('project',), 'default': ('default',), 'both': ('project', 'default')}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('sections', nargs='*', metavar='SECTION',
                        help=f'sections to run (default: all): {", ".join(SECTIONS)}')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')
    parser.add_argument('--dds', choices=list(DDS_CHOICES), default='both',
                        help="e2e's and camera_live's DDS transport (default: both, one after "
                        "the other): 'project' is config/fastdds_loopback.xml (32 MB "
                        "shared-memory segments), 'default' is Fast DDS's default 512 kB "
                        'shared-memory segment, where a 3 MB cloud or a 1.5 MB image travels '
                        'in fragments')


def run(args: argparse.Namespace) -> int:
    unknown = [name for name in args.sections if name not in SECTIONS]
    if unknown:
        choices = ', '.join(SECTIONS)
        raise ConfigError(f'unknown section {", ".join(unknown)} (choose from {choices})')
    machine = f'{platform.machine()} {platform.processor()}'.strip()
    results: dict[str, object] = {'machine': machine, 'cpu_threads': os.cpu_count()}
    for name in args.sections or list(SECTIONS):
        module_name, func_name = SECTIONS[name].split(':')
        kwargs = {'dds': DDS_CHOICES[args.dds]} if name in ('e2e', 'camera_live') else {}
        section = getattr(importlib.import_module(module_name), func_name)(**kwargs)
        if not args.json:
            print(f'[{name}]')
            width = max([28, *map(len, section)])
            for key, value in section.items():
                print(f'  {key:<{width}} {value:.3f}' if isinstance(value, float) else
                      f'  {key:<{width}} {value}')
        results.update(section)
    if args.json:
        print(json.dumps(results))
    return 0
