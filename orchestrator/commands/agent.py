"""``hilswarm agent``: run one agent of an experiment in this process and join a running bus.

Used for multi-machine runs: the orchestrator runs with ``--remote NAME`` (it does not start
that agent) and a TLS endpoint for other machines (``--listen tls/0.0.0.0:7447``); it writes
the agent's credentials file (``agent.NAME.cred`` in the run's folder, see ``hilswarm ps``).
Copy that file (mode 0600) to the machine the robot is plugged into, then::

    hilswarm agent --credentials agent.leader.cred --experiment graphs/lead_follow.toml \\
        --name leader --link leader=/dev/ttyUSB0

The credentials file names the run and its endpoints (``--connect tls/HOST:PORT`` overrides
them). On the orchestrator's own machine no file is needed: the run is found by name in the
run registry. Ctrl-C brings the agent to safe mode and stops it.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Container
from pathlib import Path

from hilswarm.agents.agent import run_agent
from hilswarm.agents.registry import add_search_path
from hilswarm.orchestrator.bus_access import agent_user
from hilswarm.orchestrator.commands.overrides import overrides_from_args
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.launcher import agent_config_for
from hilswarm.orchestrator.run_target import add_target_arguments, target_from_args

HELP = "start one agent process that joins a running experiment"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm agent``."""
    parser.add_argument("--experiment", type=Path, required=True, help="experiment file")
    parser.add_argument("--name", required=True, help="which agent of the experiment to run")
    parser.add_argument(
        "--link", action="append", default=[], metavar="NAME=URL", help="override a link"
    )
    add_target_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Run the agent until the experiment stops it."""
    # Only this agent's board is on this machine: the others' devices are checked where they run.
    others = _AllBut(args.name)
    overrides = overrides_from_args(args)
    elsewhere = sorted(set(overrides.get("links", {})) - {args.name})
    if elsewhere:
        print(
            f"hilswarm agent: --link for {', '.join(elsewhere)}: this process runs only agent "
            f"{args.name!r} (each agent's link is given where that agent runs)",
            file=sys.stderr,
        )
        return 2
    experiment = load_experiment(args.experiment, overrides=overrides, remote=others)
    add_search_path(experiment.path.parent)  # user "module:Class" names beside the file
    if args.name not in experiment.agent_names:
        known = ", ".join(experiment.agent_names)
        print(
            f"hilswarm agent: no agent {args.name!r} in {args.experiment}; agents: {known}",
            file=sys.stderr,
        )
        return 2
    target = target_from_args(args, experiment.name, agent_user(args.name))
    config = agent_config_for(experiment, args.name, run_id=target.keys.run_id)
    return run_agent(config, target.endpoints, target.security)


class _AllBut(Container[str]):
    """Every agent name except one (the agents that are remote from ``hilswarm agent``)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __contains__(self, item: object) -> bool:
        return item != self.name
