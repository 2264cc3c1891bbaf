"""How busy the machine's CPUs are: busy and total CPU time from ``/proc/stat`` (Linux).

Two readings of :func:`read_cpu_times` a while apart give, through :func:`busy_fraction`, the
share of all the machine's CPU time that was busy in between, whoever's work it was. The run
tally puts it into its overload warning (many late realtime ticks: the CPUs full, or a slow
agent or link on idle CPUs), and the benchmarks print it beside their figures.

Busy is everything but idle and I/O wait: user, nice, system, hard and soft interrupts, and
steal (in a virtual machine, time the host gave to something else). Guest time is inside user
already and is not added again.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The unit of ``/proc/stat``'s times [1/s].
_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
#: Where the kernel keeps them.
PROC_STAT = Path("/proc/stat")


def parse_cpu_times(text: bytes) -> tuple[float, float]:
    """``(busy, total)`` CPU time [s] of all the machine's CPUs from ``/proc/stat``'s contents.

    Raises:
        ValueError: ``text`` does not start with the aggregate ``cpu`` line.
    """
    fields = text.split(b"\n", 1)[0].split()
    if len(fields) < 9 or fields[0] != b"cpu":
        raise ValueError(f"not the contents of /proc/stat: {text[:40]!r}")
    user, nice, system, idle, iowait, irq, softirq, steal = (int(x) for x in fields[1:9])
    busy = user + nice + system + irq + softirq + steal
    return busy / _CLOCK_TICKS, (busy + idle + iowait) / _CLOCK_TICKS


def read_cpu_times(path: Path = PROC_STAT) -> tuple[float, float] | None:
    """``(busy, total)`` CPU time [s] of the machine so far; ``None`` where the system does not
    give it (no ``/proc/stat``, or one not understood)."""
    try:
        return parse_cpu_times(path.read_bytes())
    except (OSError, ValueError):
        return None


def busy_fraction(first: tuple[float, float], last: tuple[float, float]) -> float:
    """The busy share [0, 1] of the CPU time between two readings (NaN when none passed)."""
    total = last[1] - first[1]
    return (last[0] - first[0]) / total if total > 0 else float("nan")
