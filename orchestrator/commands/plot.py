"""``hilswarm plot FILE --out DIR``: PNG plots of a run recording.

Exit status: 0 plots written, 1 nothing plottable in the file (no folder is left behind), 2
bad input (a missing file, a directory or a file that is not MCAP, an ``--out`` that cannot be
written -- checked before anything is drawn --, an unknown ``--agent`` or ``--field``, a bad
``--xy``: the message lists the valid names).
"""

from __future__ import annotations

import argparse

HELP = "write PNG plots of a recording"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm plot``."""
    parser.add_argument("file", help="MCAP recording of a run")
    parser.add_argument(
        "-o", "--out", default=None, help="output folder (default: <recording name>_plots)"
    )
    parser.add_argument(
        "--xy",
        default=None,
        metavar="I,J",
        help="entries of y that are the x and y position for the path plot, by index or name "
        "(e.g. x,y; default 0,1, and no path plot when y has fewer entries)",
    )
    parser.add_argument(
        "--agent", action="append", default=None, help="only this agent (repeatable)"
    )
    parser.add_argument(
        "--field",
        action="append",
        default=None,
        help="only this entry of y or u, by name (repeatable), e.g. --field psi",
    )
    parser.add_argument(
        "--latency",
        action="store_true",
        help="also latency.png: where each tick's time went (controller, apply, board link, "
        "sense, bus), per agent",
    )


def _xy(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(","))


def run(args: argparse.Namespace) -> int:
    """Write the plots and list them; 0 on success."""
    from pathlib import Path  # noqa: PLC0415

    from hilswarm.orchestrator.plotting import plot_recording  # noqa: PLC0415 - matplotlib

    out = Path(args.out) if args.out else Path(args.file).with_name(f"{Path(args.file).stem}_plots")
    written = plot_recording(
        args.file,
        out,
        xy=_xy(args.xy) if args.xy is not None else None,
        agents=args.agent,
        fields=args.field,
        latency=args.latency,
    )
    if not written:
        print(f"no plottable data in {args.file}")
        return 1
    for path in written:
        print(path)
    return 0
