"""``hilswarm plot FILE --out DIR``: PNG plots of a run recording."""

from __future__ import annotations

import argparse

from hilswarm.agents.errors import RecordingError

HELP = "write PNG plots of a recording"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm plot``."""
    parser.add_argument("file", help="MCAP recording of a run")
    parser.add_argument(
        "-o", "--out", default=None, help="output folder (default: <recording name>_plots)"
    )
    parser.add_argument(
        "--xy",
        default="0,1",
        metavar="I,J",
        help="entries of y that are the x and y position for the path plot (default 0,1)",
    )
    parser.add_argument(
        "--agent", action="append", default=None, help="only this agent (repeatable)"
    )


def _indices(text: str) -> tuple[int, int]:
    parts = text.split(",")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise RecordingError(f"--xy must be two indices like 0,1, got {text!r}")
    return int(parts[0]), int(parts[1])


def run(args: argparse.Namespace) -> int:
    """Write the plots and list them; 0 on success."""
    from pathlib import Path  # noqa: PLC0415

    from hilswarm.orchestrator.plotting import plot_recording  # noqa: PLC0415 - matplotlib

    out = Path(args.out) if args.out else Path(args.file).with_name(f"{Path(args.file).stem}_plots")
    written = plot_recording(args.file, out, xy=_indices(args.xy), agents=args.agent)
    if not written:
        print(f"no plottable data in {args.file}")
        return 1
    for path in written:
        print(path)
    return 0
