"""``hilswarm stop``: bring every agent of a running experiment to safe mode and stop the run.

Example::

    hilswarm stop lead_follow            # orderly: safe mode, stop, recording closed
    hilswarm stop lead_follow --estop    # emergency: every board's outputs safe at once
    hilswarm stop lead_follow --pause    # hold ticks; --resume continues

The experiment is found by name in the run registry (``hilswarm ps``); an unknown or ambiguous
name fails at once, listing what is running. The command authenticates as the run's operator,
publishes on ``hilswarm/<exp>/<run_id>/manager/request`` (the manager forwards it to the agents
at once) and, for stop and estop, waits (bounded) until the manager reports that it stopped.
"""

from __future__ import annotations

import argparse
import sys
import threading

import zenoh
from hilswarm.agents import bus
from hilswarm.orchestrator.bus_access import OPERATOR
from hilswarm.orchestrator.cli_types import positive_float
from hilswarm.orchestrator.run_target import add_target_arguments, target_from_args

HELP = "bring every agent of a running experiment to safe mode and stop"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm stop``."""
    parser.add_argument("experiment", help="experiment name (as in its [experiment] table)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--estop", action="store_true", help="emergency stop (board e-stop)")
    group.add_argument("--pause", action="store_true", help="pause ticking")
    group.add_argument("--resume", action="store_true", help="resume ticking")
    parser.add_argument("--reason", default="", help="recorded with the command")
    add_target_arguments(parser)
    parser.add_argument("--timeout", type=positive_float, default=15.0, help="bound on waiting [s]")


def run(args: argparse.Namespace) -> int:
    """Publish the command; for stop/estop wait until the manager has stopped."""
    if args.estop:
        command = bus.ControlCommand.ESTOP
    elif args.pause:
        command = bus.ControlCommand.PAUSE
    elif args.resume:
        command = bus.ControlCommand.RESUME
    else:
        command = bus.ControlCommand.STOP
    target = target_from_args(args, args.experiment, OPERATOR)
    keys = target.keys
    matched = threading.Event()
    stopped = threading.Event()

    def on_manager_status(sample: zenoh.Sample) -> None:
        try:
            state = bus.decode_json(sample.payload.to_bytes()).get("state")
        except bus.BusMessageError:
            return
        if state == "stopped":
            stopped.set()

    def on_match(status: zenoh.MatchingStatus) -> None:
        if status.matching:
            matched.set()

    config = bus.client_config(target.endpoints, security=target.security)
    try:
        session = bus.open_session(config)
    except bus.BusConnectionError:
        ended = target.ended()
        if not ended:
            raise
        return _ended(args.experiment, target.describe(), ended, command)
    with session:
        status_sub = session.declare_subscriber(keys.manager_status, on_manager_status)
        publisher = session.declare_publisher(keys.manager_request, **bus.TICK_PATH_QOS)
        listener = publisher.declare_matching_listener(on_match)
        if bus.has_subscribers(publisher):
            matched.set()
        if not matched.wait(args.timeout):
            ended = target.ended()
            if ended:
                return _ended(args.experiment, target.describe(), ended, command)
            print(
                f"hilswarm stop: {target.describe()} does not listen on "
                f"{', '.join(target.endpoints)}",
                file=sys.stderr,
            )
            return 1
        publisher.put(bus.encode_control(command, reason=args.reason))
        if command in (bus.ControlCommand.PAUSE, bus.ControlCommand.RESUME):
            print(f"{args.experiment}: {command.value} sent")
            return 0
        if not stopped.wait(args.timeout):
            print(f"hilswarm stop: {args.experiment} did not report stopped", file=sys.stderr)
            return 1
        del status_sub, listener
    print(f"{args.experiment}: stopped")
    return 0


def _ended(experiment: str, described: str, ended: str, command: bus.ControlCommand) -> int:
    """The run ended (or is ending) before the command reached it: for stop and e-stop that is
    what was asked (its agents are safe or going safe: exit 0); pause and resume come too late
    (exit 2, as for a run that is not running)."""
    if command in (bus.ControlCommand.STOP, bus.ControlCommand.ESTOP):
        print(f"{experiment}: {described} {ended} already")
        return 0
    print(f"hilswarm stop: {described} {ended}: nothing to {command.value}", file=sys.stderr)
    return 2
