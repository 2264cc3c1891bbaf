"""Command-line overrides of an experiment file, shared by ``check``, ``graph`` and ``run``."""

from __future__ import annotations

import argparse
from typing import Any

from hilswarm.orchestrator.cli_types import positive_int
from hilswarm.orchestrator.experiment import DEFAULT_MAX_AGENTS, parse_link_overrides


def add_override_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--mode``, ``--duration``, ``--rate``, ``--link NAME=URL`` (repeatable) and
    ``--max-agents N``."""
    parser.add_argument("--mode", choices=("lockstep", "realtime"), help="override the mode")
    parser.add_argument("--duration", type=float, metavar="SECONDS", help="override duration_s [s]")
    parser.add_argument("--rate", type=float, metavar="HZ", help="override rate_hz [Hz]")
    parser.add_argument(
        "--link",
        action="append",
        default=[],
        metavar="NAME=URL",
        help="override an agent's link, e.g. --link leader=/dev/ttyUSB0 (repeatable)",
    )
    parser.add_argument(
        "--max-agents",
        type=positive_int,
        default=DEFAULT_MAX_AGENTS,
        metavar="N",
        help=f"accept up to N agents (default {DEFAULT_MAX_AGENTS}; one process per agent)",
    )


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The ``overrides`` mapping for :func:`load_experiment` from parsed arguments.

    Raises:
        ExperimentError: a ``--link`` item that is not ``NAME=URL``.
    """
    overrides: dict[str, Any] = {}
    if getattr(args, "mode", None) is not None:
        overrides["mode"] = args.mode
    if getattr(args, "duration", None) is not None:
        overrides["duration_s"] = args.duration
    if getattr(args, "rate", None) is not None:
        overrides["rate_hz"] = args.rate
    links = getattr(args, "link", None) or []
    if links:
        overrides["links"] = parse_link_overrides(links)
    return overrides
