"""``hilswarm replay RUN.mcap``: run recorded inputs through the controllers again, compare.

Example::

    hilswarm replay out/lead_follow.mcap
    hilswarm replay out/lead_follow.mcap --set leader.kp=2.0
    hilswarm replay out/lead_follow.mcap --controller f1=my_module:MyFollower --json

Exit status: 0 done (divergence is a result, not an error), 1 nothing to replay (a recording
with no controller steps, e.g. cut short before its first tick), 2 bad input (unknown agent,
controller or parameter; a missing file, a directory, not an MCAP file, not a run recording;
an ``--out`` that cannot be written, checked before anything is replayed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

HELP = "replay a recording through its controllers (or changed ones) and report divergence"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm replay``."""
    parser.add_argument("file", type=Path, help="MCAP recording of a run")
    parser.add_argument(
        "--controller",
        action="append",
        default=[],
        metavar="AGENT=CONTROLLER",
        help="replay AGENT with another controller (registry name or module:Class; repeatable)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="AGENT.PARAM=VALUE",
        help="change a controller parameter for the replay (value in TOML syntax; repeatable)",
    )
    parser.add_argument("--agent", action="append", default=None, help="only this agent")
    parser.add_argument(
        "--json", action="store_true", help="one JSON object per agent per line (stable output)"
    )
    parser.add_argument(
        "-o", "--out", type=Path, default=None, help="plot folder (default <recording>_replay)"
    )
    parser.add_argument("--no-plot", action="store_true", help="write no plots")


def _controllers(items: list[str]) -> dict[str, str]:
    result = {}
    for item in items:
        agent, sep, name = item.partition("=")
        if not sep or not agent.strip() or not name.strip():
            raise ValueError(f"--controller: expected AGENT=CONTROLLER, got {item!r}")
        result[agent.strip()] = name.strip()
    return result


def _params(items: list[str]) -> dict[str, dict[str, Any]]:
    from hilswarm.orchestrator.commands.set import parse_assignments  # noqa: PLC0415

    result: dict[str, dict[str, Any]] = {}
    for item in items:
        target, sep, _ = item.partition("=")
        agent, dot, param = target.partition(".")
        if not sep or not dot or not agent.strip() or not param.strip():
            raise ValueError(f"--set: expected AGENT.PARAM=VALUE, got {item!r}")
        value = parse_assignments([f"{param.strip()}={item.partition('=')[2]}"])
        result.setdefault(agent.strip(), {}).update(value)
    return result


def run(args: argparse.Namespace) -> int:
    """Replay and report; see the module docstring for the exit status."""
    from hilswarm.orchestrator import replay  # noqa: PLC0415 - numpy, user controllers
    from hilswarm.orchestrator.output_paths import check_output_folder  # noqa: PLC0415

    out = None if args.no_plot else args.out or args.file.with_name(f"{args.file.stem}_replay")
    try:
        controllers = _controllers(args.controller)
        params = _params(args.set)
        recording = replay.load_recording(args.file)
        if out is not None:
            check_output_folder(out, what="the replay plots")
        results = replay.replay(
            recording,
            controllers=controllers,
            params=params,
            agents=args.agent,
            search_path=Path(str(recording.experiment.get("file", "."))).parent,
        )
    except (ValueError, replay.ReplayError) as exc:
        print(f"hilswarm replay: {exc}", file=sys.stderr)
        return 2
    if not results:
        print(f"hilswarm replay: no ticks to replay in {args.file}", file=sys.stderr)
        return 1
    plots = [] if out is None else replay.plot_replay(results, out)
    for result in results:
        if args.json:
            print(json.dumps(result.as_json()))
            continue
        verdict = (
            "bit-exact"
            if result.first_divergent_tick is None
            else f"first divergent tick {result.first_divergent_tick}"
        )
        x_text = (
            "n/a (state sizes differ)"
            if result.max_abs_x_hat is None
            else (f"{result.max_abs_x_hat:.6g}")
        )
        print(
            f"{result.agent}: {result.ticks} ticks, {verdict}; max |du| "
            f"{result.max_abs_u:.6g}, max |dx_hat| {x_text}"
        )
    if not args.json:
        for path in plots:
            print(path)
    return 0
