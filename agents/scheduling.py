"""The CPU scheduling policy of an agent process: lockstep runs are batch work.

A lockstep run is a simulation that runs as fast as the machine allows: what counts is the
swarm's throughput, not when one thread gets a core. On Linux every agent thread would
otherwise run under ``SCHED_OTHER``, where a thread that wakes (a bus thread receiving a
neighbour's output, a worker woken for its tick) may preempt the one running, so on a machine
whose cores the swarm keeps busy most ticks are interrupted midway by another agent's wake-up:
measured in a lockstep 8 x 100 Hz run on two cores, each agent's worker was preempted about
once per tick. Under ``SCHED_BATCH`` a waking thread never preempts: it waits until the running
one blocks or its time slice ends (the niceness and the fair share are unchanged). Lockstep
8 x 100 Hz ran 8 % faster that way, on average over 12 alternating pairs (docs/running.md,
"Levers").

Realtime runs keep ``SCHED_OTHER``: there a tick's latency counts, and under ``SCHED_BATCH``
a thread woken by an e-stop would wait for a running thread's slice on a saturated machine
(measured in realtime runs: no gain either). In lockstep that wait is bounded by the slice
(a few ms on Linux's defaults), well within the e-stop's 20 ms.

:func:`use_batch_scheduling` switches every thread of the calling process (a Linux policy
is per thread; threads started later inherit their creator's); on systems without
``SCHED_BATCH`` it does nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The calling process's threads.
TASKS = Path("/proc/self/task")


def use_batch_scheduling(tasks: Path = TASKS) -> int:
    """Put every thread of this process under ``SCHED_BATCH`` (niceness unchanged).

    Returns:
        The number of threads switched (0 where the system has no ``SCHED_BATCH``).

    Raises:
        OSError: a thread's policy could not be set (one that ended meanwhile is skipped).
    """
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is None or not tasks.is_dir():
        return 0
    switched = 0
    for task in tasks.iterdir():
        try:
            os.sched_setscheduler(int(task.name), policy, os.sched_param(0))
        except ProcessLookupError:
            continue  # the thread ended since the listing
        switched += 1
    return switched
