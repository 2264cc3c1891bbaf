"""The files of one recording: ``run.mcap``, then ``run.1.mcap``, ``run.2.mcap``, ...

A recording is split into segments when its recorder process dies and a new one continues
(:mod:`hilswarm.orchestrator.recorder_process`). Each segment is a complete MCAP file that
starts with ``/experiment``; together, in order, they hold the run's messages once each.
"""

from __future__ import annotations

from pathlib import Path


def segment_path(path: Path, index: int) -> Path:
    """Segment ``index`` of the recording ``path``: ``run.mcap``, ``run.1.mcap``, ..."""
    return path if index == 0 else path.with_name(f"{path.stem}.{index}{path.suffix or '.mcap'}")


def existing_segments(path: Path) -> list[Path]:
    """The files of the recording ``path`` that exist (itself and its ``run.N.mcap``)."""
    found = [path] if path.exists() else []
    index = 1
    while segment_path(path, index).exists():
        found.append(segment_path(path, index))
        index += 1
    return found
