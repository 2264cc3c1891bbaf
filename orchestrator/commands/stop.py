"""``hilswarm stop``: bring every agent of a running experiment to safe mode and stop the run.

Example::

    hilswarm stop lead_follow            # orderly: safe mode, stop, recording closed
    hilswarm stop lead_follow --estop    # emergency: every board's outputs safe at once
    hilswarm stop lead_follow --pause    # hold ticks; --resume continues

The command publishes on ``hilswarm/<exp>/control`` and waits (bounded) until the instance
manager reports that it stopped.
"""

from __future__ import annotations

import argparse
import sys
import threading

import zenoh
from hilswarm.agents import bus

HELP = "bring every agent of a running experiment to safe mode and stop"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm stop``."""
    parser.add_argument("experiment", help="experiment name (as in its [experiment] table)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--estop", action="store_true", help="emergency stop (board e-stop)")
    group.add_argument("--pause", action="store_true", help="pause ticking")
    group.add_argument("--resume", action="store_true", help="resume ticking")
    parser.add_argument("--reason", default="", help="recorded with the command")
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"bus endpoint (default tcp/127.0.0.1:{bus.DEFAULT_PORT})",
    )
    parser.add_argument("--timeout", type=float, default=15.0, help="bound on waiting [s]")


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
    try:
        keys = bus.BusKeys(args.experiment)
    except ValueError as exc:
        print(f"hilswarm stop: {exc}", file=sys.stderr)
        return 2
    endpoints = args.connect or [bus.loopback_endpoint(bus.DEFAULT_PORT)]
    matched = threading.Event()
    stopped = threading.Event()

    def on_manager_status(sample: zenoh.Sample) -> None:
        if bus.decode_json(sample.payload.to_bytes()).get("state") == "stopped":
            stopped.set()

    def on_match(status: zenoh.MatchingStatus) -> None:
        if status.matching:
            matched.set()

    with bus.open_session(bus.client_config(endpoints)) as session:
        status_sub = session.declare_subscriber(keys.manager_status, on_manager_status)
        publisher = session.declare_publisher(keys.control, **bus.TICK_PATH_QOS)
        listener = publisher.declare_matching_listener(on_match)
        if bus.has_subscribers(publisher):
            matched.set()
        if not matched.wait(args.timeout):
            print(
                f"hilswarm stop: no running experiment {args.experiment!r} on "
                f"{', '.join(endpoints)}",
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
