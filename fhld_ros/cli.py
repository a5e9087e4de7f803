"""`fhld` command line: one subcommand per module.

Each module named in COMMANDS provides ``add_arguments(parser)`` and ``run(args) -> int`` and
keeps heavy imports (torch, rclpy) inside ``run`` so that ``fhld --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from fhld_ros.errors import CliError

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    'bench': ('fhld_ros.bench', 'time the pipeline stages on this machine (medians)'),
    'replay': ('fhld_ros.replay', 'run the detector pipeline over a bag on bag time'),
    'play': ('fhld_ros.play', 'publish a bag over DDS in real time with /clock'),
    'demo': ('fhld_ros.demo', 'simulate a drive, detect lanes, score them and draw a picture'),
    'eval': ('fhld_ros.evaluate',
             'score predicted /lanes against /lanes_gt (FHLD point metric, ONCE-3DLanes metric)'),
    'simulate': ('fhld_ros.data.simulate', 'write a simulated road scene as a rosbag2 MCAP bag'),
    'testset': ('fhld_ros.testset', 'score detectors on the fixed held-out simulated test set'),
    'train': ('fhld_ros.train', 'train the FHLD detector on cached simulator windows'),
}

__all__ = ['COMMANDS', 'CliError', 'build_parser', 'main']


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='fhld', description='FHLD lane detection tools (simulate, replay, eval, bench, ...)')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        module = importlib.import_module(module_name)
        cmd = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(cmd)
        cmd.set_defaults(_module=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._module.run(args) or 0)
    except CliError as exc:
        print(f'fhld {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
