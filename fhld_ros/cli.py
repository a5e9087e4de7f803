"""`fhld` command line: one subcommand per module.

Each module named in COMMANDS provides ``add_arguments(parser)`` and ``run(args) -> int``. Only
the chosen subcommand's module is imported, so ``fhld --help`` needs neither torch nor rclpy and
a command's module imports what it uses at its top.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from fhld_ros.errors import ConfigError

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    'autolabel': ('fhld_ros.commands.autolabel',
                  '3D lane labels from 2D image lane labels and the LiDAR sweeps of a drive'),
    'autolabel-eval': ('fhld_ros.commands.autolabel_eval',
                       'fhld autolabel on held-out simulated drives, scored against the 3D GT'),
    'bench': ('fhld_ros.commands.bench', 'time the pipeline stages on this machine (medians)'),
    'replay': ('fhld_ros.commands.replay', 'run the detector pipeline over a bag on bag time'),
    'play': ('fhld_ros.ros.play', 'publish a bag over DDS in real time with /clock'),
    'demo': ('fhld_ros.commands.demo',
             'simulate a drive, detect lanes, score them and draw a picture'),
    'import': ('fhld_ros.commands.import_scans',
               'PCD files or KITTI .bin sweeps as an MCAP bag (/points, /odom from poses)'),
    'eval': ('fhld_ros.evaluation.evaluate',
             'score predicted /lanes against /lanes_gt (FHLD point metric, ONCE-3DLanes metric)'),
    'realscans': ('fhld_ros.evaluation.real_scans',
                  'detectors on the real development sweeps, scored against hand labels'),
    'simulate': ('fhld_ros.sim.simulate', 'write a simulated road scene as a rosbag2 MCAP bag'),
    'testset': ('fhld_ros.evaluation.testset',
                'score detectors on the fixed held-out simulated test set'),
    'train': ('fhld_ros.training.train', 'train the FHLD detector on cached simulator windows'),
    'salad-train': ('fhld_ros.salad.train',
                    'train SALAD, the camera detector, on simulated camera drives'),
    'salad-average': ('fhld_ros.salad.average',
                      'the mean of the weights of SALAD checkpoints fine-tuned from one another'),
    'salad-calibrate': ('fhld_ros.salad.calibrate',
                        "SALAD weights with their far depth calibrated on held-out images' lanes"),
    'salad-eval': ('fhld_ros.salad.evaluate',
                   'score SALAD with the ONCE-3DLanes metric on held-out drives / datasets'),
    'salad-labels2d': ('fhld_ros.commands.salad_labels2d',
                       "SALAD's lanes as 2D labels of a bag's images (for fhld autolabel)"),
    'salad-real': ('fhld_ros.salad.real_images',
                   'SALAD on the real camera images of the development set (OpenLane scored)'),
}

__all__ = ['COMMANDS', 'build_parser', 'main']


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `fhld` parser; only `command` (when given) gets its arguments and module."""
    parser = argparse.ArgumentParser(
        prog='fhld', description='FHLD lane detection tools (simulate, replay, eval, bench, ...)')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        cmd = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(cmd)
            cmd.set_defaults(_module=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # `fhld` has no options of its own but -h: the first word that is not one names the command
    chosen = next((word for word in argv if not word.startswith('-')), None)
    args = build_parser(chosen).parse_args(argv)
    try:
        return int(args._module.run(args) or 0)
    except ConfigError as exc:
        print(f'fhld {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
