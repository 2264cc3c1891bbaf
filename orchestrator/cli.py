"""The ``hilswarm`` command line.

Each subcommand lives in its own module under :mod:`hilswarm.orchestrator.commands` and exposes
``HELP: str``, ``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only for
the command being run, so ``hilswarm check`` starts fast and never imports Zenoh. For ``run``
the agents' fork server and the recorder process are started first, so that their imports
and the command's overlap (:data:`FORKS_AGENTS`).

Exit status: 0 success, 1 the run failed, 2 bad input (file, key or value), 130 interrupted,
141 (128 + SIGPIPE, as a shell tool killed by it) the reader of the output went away
(``hilswarm graph x.toml --json | head -1``): the rest of the output is dropped, quietly.

Ctrl-C at any moment :func:`main` runs -- also while a command's modules (Zenoh, numpy, ...)
are still being imported, the first second or so -- ends with one line and status 130;
commands that handle SIGINT themselves (``run``: agents to safe mode, the recording closed)
take over once they have set up. (Only the interpreter's own start-up, before this module is
imported, some 30 ms, is out of its reach.)
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from types import FrameType, ModuleType
from typing import TYPE_CHECKING

from hilswarm.agents.errors import HilswarmError

if TYPE_CHECKING:
    import subprocess

    from hilswarm.agents.spawner import ForkServer

#: Exit status when the reader of the output closed its end of the pipe (128 + SIGPIPE).
BROKEN_PIPE = 141
#: Exit status after Ctrl-C (128 + SIGINT).
INTERRUPTED = 130

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
    parser.add_argument(
        "--version",
        action=_VersionAction,
        help="print hilswarm's version and the board wire protocol versions it speaks",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (_, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            _command_module(name).add_arguments(p)
        _accept_verbose(p)
    return parser


def _accept_verbose(parser: argparse.ArgumentParser) -> None:
    """``-v`` after the command too (``hilswarm run x.toml -v``), and after its own
    subcommand (``hilswarm xbee scan -v``)."""
    parser.add_argument(
        "-v",
        "--verbose",
        dest=_VERBOSE_AFTER,
        action="count",
        default=0,
        help="more log output (-vv: debug); the same as before the command",
    )
    for action in parser._actions:  # argparse lists a parser's subcommands only here
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _accept_verbose(child)


#: Where the command's own ``-v`` counts go; :func:`parse_arguments` adds them to ``verbose``.
_VERBOSE_AFTER = "verbose_after_command"


def parse_arguments(parser: argparse.ArgumentParser, args: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args(args)`` with every ``-v``, before the command and after it, counted
    in ``verbose``."""
    parsed = parser.parse_args(args)
    parsed.verbose += getattr(parsed, _VERBOSE_AFTER, 0)
    with contextlib.suppress(AttributeError):
        delattr(parsed, _VERBOSE_AFTER)
    return parsed


def version_text() -> str:
    """``hilswarm 0.1.0 (board wire protocol 2; boards speaking 1, 2 accepted)``."""
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415 - --version

    from hilswarm.agents.link.board import (  # noqa: PLC0415 - --version only
        PROTOCOL_VERSION,
        SUPPORTED_PROTOCOL_VERSIONS,
    )

    try:
        package = version("hilswarm")
    except PackageNotFoundError:
        package = "unknown (not installed)"
    accepted = ", ".join(str(v) for v in sorted(SUPPORTED_PROTOCOL_VERSIONS))
    return (
        f"hilswarm {package} (board wire protocol {PROTOCOL_VERSION}; "
        f"boards speaking {accepted} accepted)"
    )


class _VersionAction(argparse.Action):
    """``--version``: the text is made only when asked for (no import at every start)."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *_args: object, **_kwargs: object) -> None:
        print(version_text())
        parser.exit()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hilswarm`` console script."""
    try:
        return _main(argv)
    except KeyboardInterrupt:  # anywhere: while importing a command's modules, or running it
        print("hilswarm: interrupted", file=sys.stderr)
        return INTERRUPTED


#: Commands that fork agents and record on this machine: their fork server and recorder
#: process are started before the command's modules are imported, so that their imports
#: (~1 s of CPU each) and the command's own run at once, on two cores. The command finds
#: them as ``args.fork_server`` and ``args.recorder_process``; what it did not take over is
#: ended when it returns.
FORKS_AGENTS = frozenset({"run"})


def _main(argv: Sequence[str] | None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in args_list if not a.startswith("-")), None)
    if command not in COMMANDS:
        command = None
    server, recorder = _early_processes(command)
    try:
        return _command(args_list, command, server, recorder)
    finally:
        if server is not None:  # unused, or already closed by the command: both are fine
            server.close()
        if recorder is not None and recorder.poll() is None:  # never given its set-up
            recorder.terminate()
            recorder.wait()


def _early_processes(
    command: str | None,
) -> tuple[ForkServer | None, subprocess.Popen[bytes] | None]:
    if command not in FORKS_AGENTS:
        return None, None
    from hilswarm.agents.spawner import ForkServer, SpawnError  # noqa: PLC0415 - run only
    from hilswarm.orchestrator.recorder_spawn import start_recorder_process  # noqa: PLC0415

    server = recorder = None  # if one cannot start, the command starts its own and says why
    with contextlib.suppress(SpawnError):
        server = ForkServer()
    with contextlib.suppress(OSError):
        recorder = start_recorder_process()
    return server, recorder


def _command(
    args_list: list[str],
    command: str | None,
    server: ForkServer | None,
    recorder: subprocess.Popen[bytes] | None,
) -> int:
    with _exit_on_interrupt():
        try:
            parser = build_parser(command)
        except ImportError as exc:
            print(f"hilswarm: command {command!r} is not available: {exc}", file=sys.stderr)
            return 1
        args = parse_arguments(parser, args_list)
        logging.basicConfig(
            level=logging.WARNING - 10 * min(args.verbose, 2),
            format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        )
    if server is not None:
        args.fork_server = server
    if recorder is not None:
        args.recorder_process = recorder
    try:
        code = int(_command_module(args.command).run(args) or 0)
        sys.stdout.flush()  # here, not at exit: a closed pipe is handled below
    except BrokenPipeError:
        _drop_output()
        return BROKEN_PIPE
    except HilswarmError as exc:
        print(f"hilswarm {args.command}: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError | TypeError | LookupError) else 1
    return code


def _exit_at_once(_signum: int, _frame: FrameType | None) -> None:
    os.write(2, b"hilswarm: interrupted\n")
    os._exit(INTERRUPTED)


@contextlib.contextmanager
def _exit_on_interrupt() -> Iterator[None]:
    """While a command is set up (its modules imported, its arguments parsed), Ctrl-C exits at
    once: nothing has started yet, so nothing needs undoing. Not as a ``KeyboardInterrupt``:
    raised inside the import machinery, one can be swallowed ("Exception ignored in
    ... _get_module_lock") and the Ctrl-C lost. Python's own handler is back for the command.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return
    previous = signal.signal(signal.SIGINT, _exit_at_once)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


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
