"""The ``hilswarm`` command line.

Each subcommand lives in its own module under :mod:`hilswarm.orchestrator.commands` and exposes
``HELP: str``, ``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only for
the command being run, so ``hilswarm check`` starts fast and never imports Zenoh.

Exit status: 0 success, 1 the run failed, 2 bad input (file, key or value), 130 interrupted,
141 (128 + SIGPIPE, as a shell tool killed by it) the reader of the output went away
(``hilswarm graph x.toml --json | head -1``): the rest of the output is dropped, quietly.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence
from types import ModuleType

from hilswarm.agents.errors import HilswarmError

#: Exit status when the reader of the output closed its end of the pipe (128 + SIGPIPE).
BROKEN_PIPE = 141

#: command -> (module, one-line help). Order is the order shown by --help.
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("run", "run an experiment file (one process per agent, recorded to MCAP)"),
    "check": ("check", "validate an experiment file without starting anything"),
    "graph": ("graph", "show graph facts (connectivity, degrees, algebraic connectivity)"),
    "set": ("set", "change controller parameters of a running agent"),
    "stop": ("stop", "bring every agent of a running experiment to safe mode and stop"),
    "ps": ("ps", "list running experiments (name, run id, endpoint, pid, mode, tick, agents)"),
    "plot": ("plot", "write PNG plots of a recording"),
    "recover": ("recover", "rewrite an MCAP file whose writer was killed"),
    "replay": (
        "replay",
        "replay a recording through its controllers (or changed ones) and report divergence",
    ),
    "agent": ("agent", "start one agent process that joins a running experiment"),
    "gateway": ("gateway", "run the XBee gateway of an experiment (joins a running bus)"),
    "xbee": ("xbee", "XBee radios: node discovery (scan) and configuration (setup)"),
    "new": ("new", "write a skeleton vehicle or device with its test and experiment file"),
    "calibrate": ("calibrate", "fit and plot a calibration table from measured pairs"),
    "mocap": ("mocap", "list the bodies a mocap system sees, with rate and position"),
}


def _command_module(name: str) -> ModuleType:
    module_name, _ = COMMANDS[name]
    return importlib.import_module(f"hilswarm.orchestrator.commands.{module_name}")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Build the parser; only ``command``'s module is imported for its arguments."""
    parser = argparse.ArgumentParser(
        prog="hilswarm",
        description="Hardware-in-the-loop control of swarms of small Arduino vehicles.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            _command_module(name).add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hilswarm`` console script."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in args_list if not a.startswith("-")), None)
    if command not in COMMANDS:
        command = None
    try:
        parser = build_parser(command)
    except ImportError as exc:
        print(f"hilswarm: command {command!r} is not available: {exc}", file=sys.stderr)
        return 1
    args = parser.parse_args(args_list)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        code = int(_command_module(args.command).run(args) or 0)
        sys.stdout.flush()  # here, not at exit: a closed pipe is handled below
    except BrokenPipeError:
        _drop_output()
        return BROKEN_PIPE
    except KeyboardInterrupt:
        print("hilswarm: interrupted", file=sys.stderr)
        return 130
    except HilswarmError as exc:
        print(f"hilswarm {args.command}: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError | TypeError | LookupError) else 1
    return code


def _drop_output() -> None:
    """The reader of standard output went away: send what is still buffered, and anything
    written later, to ``/dev/null`` (Python's recipe), so the flush at exit raises no second
    ``BrokenPipeError``."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
