"""The benchmarks' CPU sampler: the machine's busy CPU share between its readings."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from types import ModuleType

import pytest


@pytest.fixture(scope="module")
def cpu_sampler(benchmarks_on_path: Path) -> ModuleType:
    """The sampler module of the benchmarks."""
    import cpu_sampler

    return cpu_sampler


def test_a_sampler_reports_the_machine_busy_while_a_process_burns(
    cpu_sampler: ModuleType,
) -> None:
    """This process burns 0.3 s of CPU between start and stop: the machine was busy for at
    least that share of one CPU, and never more than all of them."""
    sampler = cpu_sampler.CpuSampler([os.getpid()], period_s=0.05)
    assert math.isnan(sampler.machine_busy())
    sampler.start()
    started, wall = time.process_time(), time.monotonic()
    while time.process_time() - started < 0.3 and time.monotonic() - wall < 10:
        pass
    sampler.stop()
    elapsed = time.monotonic() - wall
    busy = sampler.machine_busy()
    assert sampler.total_s() > 0.15
    assert 0.15 / elapsed / os.cpu_count() <= busy <= 1.0
