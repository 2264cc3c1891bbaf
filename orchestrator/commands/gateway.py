"""``hilswarm gateway``: run an experiment's XBee gateway in this process.

For runs over several hosts: the machine the coordinator radio is plugged into runs the gateway,
joining the experiment's bus, while ``hilswarm run --remote-gateway --listen tls/0.0.0.0:7447``
runs the rest. Copy the run's ``gateway.cred`` (from the run's folder, see ``hilswarm ps``) to
the gateway's machine::

    hilswarm gateway graphs/xbee_swarm.toml --credentials gateway.cred

On the orchestrator's machine the run is found by name in the run registry.

Ctrl-C stops it. Exit status: 0 stopped, 1 the coordinator or the bus failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from hilswarm.agents.xbee.gateway_process import plan_for, serve
from hilswarm.orchestrator.bus_access import GATEWAY
from hilswarm.orchestrator.commands.overrides import overrides_from_args
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.run_target import add_target_arguments, target_from_args

HELP = "run the XBee gateway of an experiment (one coordinator radio for every xbee:// robot)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm gateway``."""
    parser.add_argument("file", type=Path, help="experiment file (TOML)")
    parser.add_argument(
        "--link", action="append", default=[], metavar="NAME=URL", help="override a link"
    )
    add_target_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C."""
    experiment = load_experiment(args.file, overrides=overrides_from_args(args))
    plan = plan_for(experiment)
    if plan is None:
        print(f"hilswarm gateway: no agent of {args.file} links through xbee://", file=sys.stderr)
        return 2
    target = target_from_args(args, experiment.name, GATEWAY)
    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return serve(
            plan, target.endpoints, stop, run_id=target.keys.run_id, security=target.security
        )
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
