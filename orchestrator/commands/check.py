"""``hilswarm check FILE``: validate an experiment file without starting anything.

Prints every problem as ``file:key: reason`` and exits 2 when there is any; otherwise prints a
short summary (agents, rate, ticks, graph facts) and any warnings, and exits 0.

``hilswarm check --schema [PATH]`` prints (or writes to PATH) the JSON Schema of experiment
files, generated from :mod:`hilswarm.orchestrator.schema`, for editors (taplo, VS Code).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hilswarm.orchestrator.checks import CheckReport, check_file
from hilswarm.orchestrator.commands.overrides import add_override_arguments, overrides_from_args

HELP = "validate an experiment file without starting anything"
#: Agents listed one per line in the summary of a valid file (a large swarm gets a count).
SUMMARY_AGENTS = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm check``."""
    parser.add_argument("file", nargs="?", help="experiment file (TOML)")
    add_override_arguments(parser)
    parser.add_argument(
        "--schema",
        nargs="?",
        const="-",
        metavar="PATH",
        help="print the JSON Schema of experiment files (or write it to PATH) and exit",
    )
    parser.add_argument(
        "--strict", action="store_true", help="treat warnings as problems (exit 2 on any)"
    )


def run(args: argparse.Namespace) -> int:
    """Check ``args.file``; 0 when valid, 2 when there are problems."""
    if args.schema is not None:
        return write_schema(args.schema)
    if args.file is None:
        print("hilswarm check: give an experiment file (or --schema)", file=sys.stderr)
        return 2
    report = check_file(args.file, overrides=overrides_from_args(args), max_agents=args.max_agents)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if report.problems or (args.strict and report.warnings):
        count = len(report.problems) + (len(report.warnings) if args.strict else 0)
        for problem in report.problems:
            print(problem, file=sys.stderr)
        print(
            f"hilswarm check: {count} problem{'s' if count != 1 else ''} in {args.file}",
            file=sys.stderr,
        )
        return 2
    print(summary(report))
    return 0


def summary(report: CheckReport) -> str:
    """One short paragraph describing a valid experiment."""
    experiment = report.raise_for_problems()
    facts = report.facts
    lines = [
        f"ok: {experiment.name} ({report.path}): {len(experiment.agents)} agents, "
        f"{experiment.rate_hz:g} Hz, {experiment.duration_s:g} s ({experiment.n_ticks} ticks), "
        f"{experiment.mode}, on agent loss: {experiment.on_agent_loss}"
    ]
    if facts is not None:
        if facts.strongly_connected:
            tree = "strongly connected"
        elif facts.roots:
            tree = f"spanning tree from {', '.join(facts.roots)}"
        else:
            tree = "no spanning tree"
        lines.append(
            f"graph: {facts.n_edges} edges, "
            f"{'connected' if facts.weakly_connected else 'NOT connected'}, {tree}"
            + (
                f", lambda_2 = {facts.algebraic_connectivity:.4g}"
                if facts.algebraic_connectivity is not None
                else ""
            )
        )
    for spec in experiment.agents[:SUMMARY_AGENTS]:
        link = spec.link or "(no board)"
        if spec.name in report.unused_links:
            link = f"(no board; link {spec.link} not used)"
        lines.append(f"  {spec.name}: {spec.vehicle} via {link}, controller {spec.controller}")
    if len(experiment.agents) > SUMMARY_AGENTS:
        lines.append(f"  ... and {len(experiment.agents) - SUMMARY_AGENTS} more agents")
    return "\n".join(lines)


def write_schema(target: str) -> int:
    """Print the JSON Schema (``target`` ``"-"``) or write it to the file ``target``."""
    from hilswarm.orchestrator.schema import json_schema_text  # noqa: PLC0415 - only here

    text = json_schema_text()
    if target == "-":
        sys.stdout.write(text)
        return 0
    try:
        Path(target).write_text(text, encoding="utf-8")
    except OSError as exc:
        print(f"hilswarm check: cannot write {target}: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {target}")
    return 0
