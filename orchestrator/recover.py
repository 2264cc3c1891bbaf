"""Rewrite an MCAP recording whose writer was killed (``hilswarm recover``).

A recorder that dies (SIGKILL, power loss) leaves a file without its summary and footer, and
usually with a half-written last chunk. Such a file is read from the start with a non-seeking,
truncation-tolerant reader (:func:`hilswarm.agents.mcap_io.iter_messages` machinery): every
complete, CRC-valid chunk is kept, the read stops at the first incomplete record, and the
messages are written again into a complete MCAP file (summary, indexes and footer), which any
MCAP reader and Foxglove open.
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from hilswarm.agents import mcap_io
from hilswarm.agents.errors import HilswarmError, RecordingError
from hilswarm.orchestrator.output_paths import (
    check_output_file,
    is_no_space,
    watch_writer_errors,
)

#: The 8 bytes every MCAP file starts with.
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class RecoveryResult:
    """What :func:`recover` kept.

    Attributes:
        source: the damaged file.
        destination: the rewritten file.
        messages: number of messages kept.
        topics: messages kept per topic.
        source_bytes: size of the damaged file [bytes].
        destination_bytes: size of the rewritten file [bytes].
    """

    source: Path
    destination: Path
    messages: int
    topics: dict[str, int] = field(default_factory=dict)
    source_bytes: int = 0
    destination_bytes: int = 0


class NoSpaceError(HilswarmError, OSError):
    """The recovered file does not fit on its disk (``hilswarm recover`` exits 1)."""


def default_destination(source: Path) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap`` beside it."""
    return source.with_name(f"{source.stem}.recovered{source.suffix or '.mcap'}")


def check_mcap_magic(path: str | os.PathLike[str]) -> None:
    """Raise :class:`RecordingError` unless ``path`` exists and starts with the MCAP magic.

    The one check of "is this an MCAP file" for every command that reads a recording
    (``recover``, ``plot``, ``replay``): the message says whether the file is missing, a
    directory, or something else than MCAP.
    """
    path = Path(path)
    if path.is_dir():
        raise RecordingError(f"{path} is a directory, not an MCAP file")
    if not path.exists():
        raise RecordingError(f"{path} does not exist")
    if not path.is_file():
        raise RecordingError(f"{path} is not a regular file")
    with path.open("rb") as handle:
        head = handle.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        shown = head[:8].hex(" ") if head else "nothing (empty file)"
        raise RecordingError(
            f"{path} is not an MCAP file: it starts with {shown}, "
            f"expected the MCAP magic {MCAP_MAGIC.hex(' ')}"
        )


def recover(
    source: str | os.PathLike[str],
    destination: str | os.PathLike[str] | None = None,
    *,
    in_place: bool = False,
) -> RecoveryResult:
    """Rewrite the readable part of ``source`` as a complete MCAP file.

    Args:
        source: the damaged (or intact) MCAP file.
        destination: where to write; default ``<stem>.recovered.mcap`` beside ``source``.
        in_place: replace ``source`` by the rewritten file (``destination`` must be ``None``).

    Returns:
        The counts of what was kept.

    Raises:
        RecordingError: ``source`` is missing or not MCAP, ``destination`` is ``source``,
            ``in_place`` is combined with a destination, or the destination cannot be written
            (nothing of the destination is left behind).
        OutputPathError: the destination cannot be written (a folder, a read-only folder).
        NoSpaceError: the destination's disk (or quota) is full (``ENOSPC``, ``EDQUOT``).
    """
    source = Path(source)
    check_mcap_magic(source)
    if in_place and destination is not None:
        raise RecordingError("give either a destination or in_place, not both")
    if in_place:
        target = source.with_name(f".{source.name}.recovering")
    else:
        target = Path(destination) if destination is not None else default_destination(source)
    if target.resolve() == source.resolve():
        raise RecordingError(f"the destination {target} is the source; use in_place to replace it")
    check_output_file(target, what="the recovered recording")
    source_bytes = source.stat().st_size
    with watch_writer_errors() as writer_errors:
        try:
            mcap_io.recover(source, target)  # removes what it wrote of target when it fails
        except RecordingError as exc:
            if is_no_space(exc) or writer_errors.no_space:
                raise NoSpaceError(
                    f"no space left to write {target} (the recording has {source_bytes} "
                    "bytes): free some space or write elsewhere with -o"
                ) from exc
            raise
    topics = Counter(topic for topic, _, _ in mcap_io.iter_messages(target))
    if in_place:
        os.replace(target, source)
        target = source
    return RecoveryResult(
        source=source,
        destination=target,
        messages=sum(topics.values()),
        topics=dict(topics),
        source_bytes=source_bytes,
        destination_bytes=target.stat().st_size,
    )
