"""How busy the machine's CPUs are, from ``/proc/stat`` and ``/proc/uptime`` (Linux).

Two readings of :func:`read_cpu_times` a while apart give, through :func:`busy_fraction`, the
share of all the machine's CPU time that was busy in between, whoever's work it was. The run
tally puts it into its overload warning (many late realtime ticks: the CPUs full, or a slow
agent or link on idle CPUs), and the benchmarks print it beside their figures.

Busy time is the CPUs' time (the uptime times the CPUs online) less their idle and I/O-wait
time. It is not the sum of ``/proc/stat``'s busy fields: without precise CPU accounting
(``CONFIG_VIRT_CPU_ACCOUNTING_GEN``, off in common kernels) the kernel charges each scheduler
tick (250 Hz on the development machine) to whatever runs at that instant, and a swarm's
periodic bursts fall between ticks: a 50 Hz run of 8 agents read 3 % busy that way where its
processes' own CPU made 16 %. The idle time is kept precisely (the kernel times each idle
period), so one minus the idle share is right: a burst of 2 ms every 20 ms on one of two CPUs
read 5.5 % busy (the process's own CPU: 5.2 %) where the busy fields read 0.2 %.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The unit of ``/proc/stat``'s times [1/s].
_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
#: Where the kernel keeps them.
PROC_STAT = Path("/proc/stat")
PROC_UPTIME = Path("/proc/uptime")


def parse_cpu_times(stat: bytes, uptime: bytes) -> tuple[float, float]:
    """``(busy, total)`` CPU time [s] of all the machine's CPUs from the contents of
    ``/proc/stat`` (its ``cpu`` lines at least) and ``/proc/uptime``, read together.

    ``total`` is the uptime times the CPUs online (counted from the ``cpuN`` lines), ``busy``
    that less the CPUs' idle and I/O-wait time (module doc). Only differences between two
    readings mean something.

    Raises:
        ValueError: the contents are not those of the two files.
    """
    lines = stat.split(b"\n")
    fields = lines[0].split()
    if len(fields) < 6 or fields[0] != b"cpu":
        raise ValueError(f"not the contents of /proc/stat: {stat[:40]!r}")
    cpus = sum(1 for line in lines[1:] if line.startswith(b"cpu"))
    if cpus == 0:
        raise ValueError(f"no cpuN line in /proc/stat: {stat[:80]!r}")
    try:
        up_s = float(uptime.split()[0])
    except (IndexError, ValueError) as exc:
        raise ValueError(f"not the contents of /proc/uptime: {uptime[:40]!r}") from exc
    idle_s = (int(fields[4]) + int(fields[5])) / _CLOCK_TICKS
    total = up_s * cpus
    return total - idle_s, total


def read_cpu_times(
    stat: Path = PROC_STAT, uptime: Path = PROC_UPTIME
) -> tuple[float, float] | None:
    """``(busy, total)`` CPU time [s] of the machine so far (:func:`parse_cpu_times`);
    ``None`` where the system does not give it (no such files, or ones not understood)."""
    try:
        return parse_cpu_times(stat.read_bytes(), uptime.read_bytes())
    except (OSError, ValueError):
        return None


def busy_fraction(first: tuple[float, float], last: tuple[float, float]) -> float:
    """The busy share [0, 1] of the CPU time between two readings (NaN when none passed;
    clipped to [0, 1]: the two files are read a moment apart, and are kept to 10 ms)."""
    total = last[1] - first[1]
    if total <= 0:
        return float("nan")
    return min(1.0, max(0.0, (last[0] - first[0]) / total))
