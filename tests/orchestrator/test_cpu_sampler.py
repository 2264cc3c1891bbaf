"""The benchmarks' CPU sampler: the machine's busy CPU time from /proc/stat."""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
HZ = os.sysconf("SC_CLK_TCK")


@pytest.fixture(scope="module")
def cpu_sampler() -> Iterator[ModuleType]:
    """The sampler module of the benchmarks."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import cpu_sampler

        yield cpu_sampler
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_busy_and_total_from_proc_stat(cpu_sampler: ModuleType) -> None:
    """user nice system idle iowait irq softirq steal guest guest_nice [clock ticks]: busy is
    all but idle and iowait; guest is inside user already."""
    text = b"cpu  100 20 30 400 50 6 7 8 90 10\ncpu0 50 10 15 200 25 3 3 4 45 5\nintr 1 2\n"
    busy, total = cpu_sampler.machine_cpu_s(text)
    assert busy == pytest.approx(171 / HZ)
    assert total == pytest.approx(621 / HZ)
    assert cpu_sampler.busy_fraction((1.0, 10.0), (2.5, 12.0)) == pytest.approx(0.75)
    assert math.isnan(cpu_sampler.busy_fraction((1.0, 10.0), (1.0, 10.0)))
    with pytest.raises(ValueError, match="not the contents of /proc/stat"):
        cpu_sampler.machine_cpu_s(b"intr 1 2\n")


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
