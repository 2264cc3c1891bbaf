"""``hilswarm set``: change controller parameters of a running agent.

Example::

    hilswarm set lead_follow f1 gain=0.8 offset="[0.5, 0.0]"

Each ``key=value`` is parsed as a TOML value (numbers, strings, arrays, inline tables); a bare
word that is not valid TOML is taken as a string. The agent applies the change between two
ticks through its ControlModel (the controller validates it first) and acknowledges it; the
change is also recorded on ``/<agent>/status``.

The experiment is found by name in the run registry (``hilswarm ps``); an unknown or ambiguous
name fails at once, listing what is running. The command authenticates as the run's operator.
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from typing import Any

from hilswarm.agents import bus
from hilswarm.orchestrator.bus_access import OPERATOR
from hilswarm.orchestrator.cli_types import positive_float
from hilswarm.orchestrator.run_target import add_target_arguments, target_from_args

HELP = "change controller parameters of a running agent"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm set``."""
    parser.add_argument("experiment", help="experiment name (as in its [experiment] table)")
    parser.add_argument("agent", help="agent name")
    parser.add_argument("assignments", nargs="+", metavar="KEY=VALUE", help="TOML values")
    add_target_arguments(parser)
    parser.add_argument(
        "--timeout", type=positive_float, default=5.0, help="bound on the answer [s]"
    )


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``["gain=0.5", "mode=fast"]`` -> ``{"gain": 0.5, "mode": "fast"}`` (values as TOML).

    Raises:
        ValueError: an item without ``=`` or with an empty key.
    """
    params: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"expected KEY=VALUE (value in TOML syntax), got {item!r}")
        try:
            params[key] = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            params[key] = text
    return params


def run(args: argparse.Namespace) -> int:
    """Send the change and print the agent's acknowledgement."""
    try:
        params = parse_assignments(args.assignments)
        bus.check_key_name(args.agent, what="agent name")
    except ValueError as exc:
        print(f"hilswarm set: {exc}", file=sys.stderr)
        return 2
    target = target_from_args(args, args.experiment, OPERATOR)
    if target.entry is not None and args.agent not in target.entry.agents:
        known = ", ".join(target.entry.agents) or "-"
        print(
            f"hilswarm set: {target.describe()} has no agent {args.agent!r}; agents: {known}",
            file=sys.stderr,
        )
        return 2
    key = target.keys.set(args.agent)
    endpoints = target.endpoints
    payload = bus.encode_json({"params": params})
    try:
        session = bus.open_session(bus.client_config(endpoints, security=target.security))
    except bus.BusConnectionError:
        ended = target.ended()
        if not ended:
            raise
        print(f"hilswarm set: {target.describe()} {ended}: nothing to set", file=sys.stderr)
        return 2
    with session:
        replies = session.get(key, payload=payload, timeout=args.timeout)
        for reply in replies:
            if reply.ok is not None:
                answer = bus.decode_json(reply.ok.payload.to_bytes())
                print(f"{args.agent}: set {answer.get('params')} at tick {answer.get('k')}")
                return 0
            error = bus.decode_json(reply.err.payload.to_bytes()) if reply.err else {}
            print(f"hilswarm set: {args.agent} refused: {error.get('error')}", file=sys.stderr)
            return 2
    ended = target.ended()
    if ended:
        print(f"hilswarm set: {target.describe()} {ended}: nothing was set", file=sys.stderr)
        return 2
    print(
        f"hilswarm set: no answer from agent {args.agent!r} of experiment {args.experiment!r} "
        f"on {', '.join(endpoints)} within {args.timeout} s",
        file=sys.stderr,
    )
    return 1
