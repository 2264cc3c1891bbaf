"""``hilswarm ps``: list the running experiments of this user (from the run registry).

Example::

    hilswarm ps
    hilswarm ps --json

The table shows per run: name, run id, orchestrator pid, mode, tick (of the run's ticks),
state, bus endpoint(s) and each agent's state. ``--json`` prints one JSON object, stable for
scripts (documented in docs/running.md)::

    {"version": 1, "runs": [{"name": ..., "run_id": ..., "endpoints": [...], "pid": ...,
      "mode": ..., "state": ..., "tick": ..., "n_ticks": ..., "agents": {name: state},
      "file": ..., "out": ..., "started": ..., "secure": ...}]}

Entries of runs whose orchestrator is gone are removed while listing.
"""

from __future__ import annotations

import argparse
import json

from hilswarm.orchestrator.run_registry import REGISTRY_VERSION, RunEntry, list_runs

HELP = "list running experiments (name, run id, endpoint, pid, mode, tick, agents)"

#: Keys of each run in ``hilswarm ps --json``, in order.
JSON_KEYS = (
    "name",
    "run_id",
    "endpoints",
    "pid",
    "mode",
    "state",
    "tick",
    "n_ticks",
    "agents",
    "file",
    "out",
    "started",
    "secure",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm ps``."""
    parser.add_argument("--json", action="store_true", help="machine-readable output")


def as_json(entries: list[RunEntry]) -> dict[str, object]:
    """The ``--json`` document of ``entries``."""
    runs = [{key: entry.to_json()[key] for key in JSON_KEYS} for entry in entries]
    return {"version": REGISTRY_VERSION, "runs": runs}


def _agents(entry: RunEntry) -> str:
    counts: dict[str, list[str]] = {}
    for name, state in entry.agents.items():
        counts.setdefault(state, []).append(name)
    if len(entry.agents) > 8:
        return ", ".join(f"{len(names)} {state}" for state, names in counts.items())
    return ", ".join(f"{name}={state}" for name, state in entry.agents.items())


def run(args: argparse.Namespace) -> int:
    """Print the running experiments."""
    entries = list_runs()
    if args.json:
        print(json.dumps(as_json(entries), indent=2))
        return 0
    if not entries:
        print("no running experiments")
        return 0
    rows = [("NAME", "RUN ID", "PID", "MODE", "TICK", "STATE", "ENDPOINT", "AGENTS")]
    for e in entries:
        tick = f"{max(e.tick, 0)}/{e.n_ticks}" if e.tick >= 0 else f"-/{e.n_ticks}"
        endpoint = " ".join(e.endpoints) + ("" if e.secure else " (insecure)")
        rows.append((e.name, e.run_id, str(e.pid), e.mode, tick, e.state, endpoint, _agents(e)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=False)), row[-1])
    return 0
