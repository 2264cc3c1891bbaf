"""``hilswarm recover FILE [-o OUT]``: rewrite an MCAP file whose writer was killed."""

from __future__ import annotations

import argparse

from hilswarm.orchestrator.recover import recover
from hilswarm.orchestrator.segments import existing_segments

HELP = "rewrite an MCAP file whose writer was killed"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm recover``."""
    parser.add_argument("file", help="the damaged MCAP file")
    target = parser.add_mutually_exclusive_group()
    target.add_argument(
        "-o", "--output", help="where to write (default: <name>.recovered.mcap beside FILE)"
    )
    target.add_argument(
        "--in-place", action="store_true", help="replace FILE by the recovered file"
    )


def run(args: argparse.Namespace) -> int:
    """Recover ``args.file``; 0 on success (a bad file raises RecordingError: exit 2)."""
    result = recover(args.file, args.output, in_place=args.in_place)
    print(
        f"recovered {result.messages} messages on {len(result.topics)} topics from "
        f"{result.source} ({result.source_bytes} bytes) into {result.destination} "
        f"({result.destination_bytes} bytes)"
    )
    for topic, count in sorted(result.topics.items()):
        print(f"  {topic}: {count}")
    others = [p for p in existing_segments(result.source)[1:] if p != result.destination]
    if others:
        print(
            f"note: the recording continues in {', '.join(str(p) for p in others)} "
            "(segments written after a recorder restart); recover any of them that needs it"
        )
    return 0
