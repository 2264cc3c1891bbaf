"""Fixtures of the multi-process integration tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from swarm_harness import RunProcess


@pytest.fixture
def runs() -> Iterator[list[RunProcess]]:
    """Runs started by a test; every one is killed (with its agents) afterwards."""
    started: list[RunProcess] = []
    try:
        yield started
    finally:
        for run in started:
            run.cleanup()
