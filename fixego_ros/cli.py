"""The ``fixego`` command: one sub-command per job, each registered by its own module.

A module listed in ``COMMANDS`` provides ``register(subparsers)``, which adds its sub-parser and
sets ``func`` (a callable taking the parsed args and returning an exit code). Modules are imported
lazily, so ``fixego ptz`` does not pay for OpenCV or rclpy.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# module path -> sub-command names it registers (names let us import only what is asked for)
COMMANDS: dict[str, tuple[str, ...]] = {
    'fixego_ros.demo.cli': ('demo',),
    'fixego_ros.evaluation.cli': ('eval',),
    'fixego_ros.experiments.paper_sim': ('paper-sim',),
    'fixego_ros.replay.cli': ('replay',),
    'fixego_ros.bags.record_cli': ('record',),
    'fixego_ros.bags.play_cli': ('play',),
    'fixego_ros.sim.cli': ('sim',),
    'fixego_ros.visca.cli': ('ptz',),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Parser with every sub-command, or only the module that owns ``only`` (fast start-up)."""
    parser = argparse.ArgumentParser(
        prog='fixego', description='Ego-motion from binocular independent fixation control.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for module, names in COMMANDS.items():
        if only is not None and only not in names:
            continue
        importlib.import_module(module).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    first = argv[0] if argv and not argv[0].startswith('-') else None
    known = any(first in names for names in COMMANDS.values())
    try:
        parser = build_parser(first if known else None)
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:       # before (or outside) a sub-command's own handling: one line, no traceback
        print('fixego: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
