"""`fhld bench`: stage timings as medians on the machine it runs on.

Each section is a function ``() -> dict[str, float]`` living next to the code it measures and
registered in SECTIONS as 'module:function'. ``fhld bench --json`` merges all sections into one
flat JSON object; ``fhld bench adapters`` runs one section.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

SECTIONS: dict[str, str] = {
    'adapters': 'msg_adapters.bench:bench_decode',
    'bev': 'fhld_ros.bev:bench_bev',
    'classical': 'fhld_ros.classical:bench_classical',
    'metrics': 'fhld_ros.metrics:bench_metrics',
    'model': 'fhld_ros.model.detector:bench_model',
    'simulator': 'fhld_ros.data.simulator:bench_simulator',
    'e2e': 'fhld_ros.bench_e2e:bench_e2e',
}


def time_median(fn: Callable[[], object], repeats: int = 20, warmup: int = 2) -> float:
    """Median wall time of ``fn()`` in milliseconds."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1e3)
    return statistics.median(samples)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('sections', nargs='*', metavar='SECTION',
                        help=f'sections to run (default: all): {", ".join(SECTIONS)}')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')


def run(args: argparse.Namespace) -> int:
    from fhld_ros.cli import CliError
    unknown = [name for name in args.sections if name not in SECTIONS]
    if unknown:
        choices = ', '.join(SECTIONS)
        raise CliError(f'unknown section {", ".join(unknown)} (choose from {choices})')
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
