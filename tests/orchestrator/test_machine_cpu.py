"""The machine's busy and total CPU time from /proc/stat (orchestrator/machine_cpu.py)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
from hilswarm.orchestrator.machine_cpu import busy_fraction, parse_cpu_times, read_cpu_times

HZ = os.sysconf("SC_CLK_TCK")


def test_busy_and_total_in_closed_form() -> None:
    """user nice system idle iowait irq softirq steal guest guest_nice [clock ticks]: busy is
    all but idle and iowait; guest is inside user already."""
    text = b"cpu  100 20 30 400 50 6 7 8 90 10\ncpu0 50 10 15 200 25 3 3 4 45 5\nintr 1 2\n"
    busy, total = parse_cpu_times(text)
    assert busy == pytest.approx(171 / HZ)
    assert total == pytest.approx(621 / HZ)
    assert busy_fraction((1.0, 10.0), (2.5, 12.0)) == pytest.approx(0.75)
    assert math.isnan(busy_fraction((1.0, 10.0), (1.0, 10.0)))  # no time passed


def test_what_is_not_proc_stat_is_refused_or_not_read(tmp_path: Path) -> None:
    for text in (b"intr 1 2\n", b"cpu 1 2 3\n", b""):
        with pytest.raises(ValueError, match="not the contents of /proc/stat"):
            parse_cpu_times(text)
    (tmp_path / "stat").write_bytes(b"garbage")
    assert read_cpu_times(tmp_path / "stat") is None
    assert read_cpu_times(tmp_path / "missing") is None


@pytest.mark.skipif(not Path("/proc/stat").exists(), reason="Linux only")
def test_the_machine_s_times_grow_and_busy_stays_a_fraction() -> None:
    first = read_cpu_times()
    assert first is not None
    end = os.times().elapsed + 0.2
    while os.times().elapsed < end:  # burn ~0.2 s of CPU (bounded by the clock)
        pass
    last = read_cpu_times()
    assert last is not None and last[1] > first[1] and last[0] > first[0]
    assert 0.0 < busy_fraction(first, last) <= 1.0
