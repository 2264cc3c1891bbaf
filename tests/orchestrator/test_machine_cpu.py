"""The machine's busy and total CPU time (orchestrator/machine_cpu.py)."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import pytest
from hilswarm.orchestrator.machine_cpu import busy_fraction, parse_cpu_times, read_cpu_times

HZ = os.sysconf("SC_CLK_TCK")
STAT = b"cpu  100 20 30 400 50 6 7 8 90 10\ncpu0 50 10 15 200 25 3 3 4 45 5\ncpu1 1\nintr 1 2\n"


def test_busy_is_the_cpus_time_less_idle_and_iowait_in_closed_form() -> None:
    """user nice system idle iowait ...: only idle (400) and iowait (50) are read, in clock
    ticks; the CPUs' time is the uptime times the two cpuN lines."""
    busy, total = parse_cpu_times(STAT, b"12.50 20.00\n")
    assert total == pytest.approx(25.0)
    assert busy == pytest.approx(25.0 - 450 / HZ)
    assert busy_fraction((1.0, 10.0), (2.5, 12.0)) == pytest.approx(0.75)
    assert busy_fraction((1.0, 10.0), (3.5, 12.0)) == 1.0  # read a moment apart: clipped
    assert math.isnan(busy_fraction((1.0, 10.0), (1.0, 10.0)))  # no time passed


def test_what_is_not_proc_stat_and_uptime_is_refused_or_not_read(tmp_path: Path) -> None:
    for stat in (b"intr 1 2\n", b"cpu 1 2 3\n", b"", b"cpu  1 2 3 4 5 6 7 8\nintr 1\n"):
        with pytest.raises(ValueError, match="/proc/stat"):
            parse_cpu_times(stat, b"1.0 2.0\n")
    for uptime in (b"", b"up\n"):
        with pytest.raises(ValueError, match="not the contents of /proc/uptime"):
            parse_cpu_times(STAT, uptime)
    (tmp_path / "stat").write_bytes(b"garbage")
    (tmp_path / "uptime").write_bytes(b"1.0 2.0\n")
    assert read_cpu_times(tmp_path / "stat", tmp_path / "uptime") is None
    assert read_cpu_times(tmp_path / "missing", tmp_path / "uptime") is None


@pytest.mark.skipif(not Path("/proc/stat").exists(), reason="Linux only")
def test_short_periodic_bursts_are_counted() -> None:
    """This process busy for 2 ms of every 10 ms for 1 s: at least most of its own CPU time is
    in the machine's busy share (the scheduler-tick sampled busy fields missed such bursts)."""
    first, own = read_cpu_times(), time.process_time()
    assert first is not None
    start = time.monotonic()
    for period in range(100):  # bounded: 100 periods of 10 ms
        due = start + (period + 1) * 0.01
        burst_end = min(due, time.monotonic() + 0.002)
        while time.monotonic() < burst_end:
            pass
        time.sleep(max(0.0, due - time.monotonic()))
    last, own = read_cpu_times(), time.process_time() - own
    assert last is not None
    share = busy_fraction(first, last)
    own_share = own / (last[1] - first[1])
    assert 0.5 * own_share <= share <= 1.0, (share, own_share)
