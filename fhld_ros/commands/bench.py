"""`fhld bench`: stage timings as medians on the machine it runs on.

Each section is a function ``() -> dict[str, float]`` in bench_stages.py (bench_e2e.py for the
node end to end), registered in SECTIONS as 'module:function' and imported only when it runs.
``fhld bench --json`` merges all sections into one flat JSON object; ``fhld bench adapters``
runs one.
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
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('sections', nargs='*', metavar='SECTION',
                        help=f'sections to run (default: all): {", ".join(SECTIONS)}')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def run(args: argparse.Namespace) -> int:
    unknown = [name for name in args.sections if name not in SECTIONS]
    if unknown:
        choices = ', '.join(SECTIONS)
        raise ConfigError(f'unknown section {", ".join(unknown)} (choose from {choices})')
    machine = f'{platform.machine()} {platform.processor()}'.strip()
    results: dict[str, object] = {'machine': machine, 'cpu_threads': os.cpu_count()}
    for name in args.sections or list(SECTIONS):
        module_name, func_name = SECTIONS[name].split(':')
        section = getattr(importlib.import_module(module_name), func_name)()
        if not args.json:
            print(f'[{name}]')
            for key, value in section.items():
                print(f'  {key:<28} {value:.3f}' if isinstance(value, float) else
                      f'  {key:<28} {value}')
        results.update(section)
    if args.json:
        print(json.dumps(results))
    return 0
