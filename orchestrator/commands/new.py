"""``hilswarm new``: write a skeleton vehicle or device with its test (and experiment file).

::

    hilswarm new vehicle my_rover [--dir DIR] [--profile uno]
        -> DIR/my_rover.py, DIR/test_my_rover.py, DIR/my_rover.toml
    hilswarm new device bumper --kind sensor [--dir DIR]
        -> DIR/bumper.py, DIR/test_bumper.py

Existing files are never overwritten; an unknown ``--profile`` or a ``--dir`` that cannot be
written is refused before anything is written (exit status 2). See docs/scaffold.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hilswarm.agents.pins import PROFILES
from hilswarm.orchestrator.scaffold import DEVICE_KINDS, plan_device, plan_vehicle, write_files

HELP = "write a skeleton vehicle or device with its test and experiment file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm new``."""
    parser.add_argument("what", choices=("vehicle", "device"), help="what to generate")
    parser.add_argument("name", help="snake_case or CamelCase name, e.g. my_rover or MyRover")
    parser.add_argument("--dir", type=Path, default=Path(), help="folder to write into (.)")
    parser.add_argument(
        "--profile",
        default="uno",
        help=f"board profile of a new vehicle ({', '.join(PROFILES)})",
    )
    parser.add_argument(
        "--kind", choices=DEVICE_KINDS, default="actuator", help="kind of a new device"
    )


def run(args: argparse.Namespace) -> int:
    """Plan, write and list the files; returns the exit status."""
    if args.what == "vehicle":
        files = plan_vehicle(args.name, args.dir, profile=args.profile)
    else:
        files = plan_device(args.name, args.dir, kind=args.kind)
    for path in write_files(files):
        print(f"wrote {path}")
    test = next(f.path for f in files if f.path.name.startswith("test_"))
    print(f"next: fill in every NotImplementedError, then: python -m pytest {test}")
    return 0
