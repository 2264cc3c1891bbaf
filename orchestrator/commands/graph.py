"""``hilswarm graph FILE``: show the facts of an experiment's communication graph."""

from __future__ import annotations

import argparse
import json
import sys

from hilswarm.orchestrator.cli_types import positive_int
from hilswarm.orchestrator.experiment import DEFAULT_MAX_AGENTS, parse_experiment
from hilswarm.orchestrator.graph_facts import graph_facts

HELP = "show graph facts (connectivity, degrees, algebraic connectivity)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm graph``."""
    parser.add_argument("file", help="experiment file (TOML)")
    parser.add_argument("--json", action="store_true", help="print the facts as JSON")
    parser.add_argument(
        "--matrix", action="store_true", help="also print the adjacency matrix (rows receive)"
    )
    parser.add_argument(
        "--max-agents",
        type=positive_int,
        default=DEFAULT_MAX_AGENTS,
        metavar="N",
        help=f"accept up to N agents (default {DEFAULT_MAX_AGENTS})",
    )


def run(args: argparse.Namespace) -> int:
    """Print the graph facts of ``args.file``; 2 when the file has problems."""
    experiment, problems = parse_experiment(args.file, max_agents=args.max_agents)
    if experiment is None:
        for problem in problems:
            print(problem, file=sys.stderr)
        print(f"hilswarm graph: {len(problems)} problem(s) in {args.file}", file=sys.stderr)
        return 2
    facts = graph_facts(experiment.agent_names, experiment.adjacency)
    if args.json:
        # stable keys, documented in docs/experiments.md (Graph facts): add, never rename
        data = {
            "names": list(facts.names),
            "adjacency": experiment.adjacency.tolist(),
            "n_edges": facts.n_edges,
            "symmetric": facts.symmetric,
            "weakly_connected": facts.weakly_connected,
            "strongly_connected": facts.strongly_connected,
            "has_spanning_tree": facts.has_spanning_tree,
            "roots": list(facts.roots),
            "leaders": list(facts.leaders),
            "isolated": list(facts.isolated),
            "in_degree": facts.in_degree,
            "out_degree": facts.out_degree,
            "algebraic_connectivity": facts.algebraic_connectivity,
            "consensus_rate": facts.consensus_rate,
            "components": [list(c) for c in facts.components],
        }
        print(json.dumps(data, indent=2))
        return 0
    print(f"experiment: {experiment.name} ({args.file})")
    print(facts.format())
    if args.matrix:
        print()
        print("A[i][j] = 1: agent i (row) receives agent j (column)")
        width = max(len(name) for name in facts.names) + len(str(len(facts.names))) + 3
        columns = " ".join(f"{j:>2}" for j in range(len(facts.names)))
        print(" " * width + columns)
        rows = experiment.adjacency.tolist()
        for i, (name, row) in enumerate(zip(facts.names, rows, strict=True)):
            label = f"{i:>2} {name}"
            print(f"{label:<{width}}" + " ".join(f"{v:>2}" for v in row))
    return 0
