"""A timed wait on a :class:`queue.SimpleQueue` that never outwaits its timeout.

CPython's ``SimpleQueue.get(timeout=t)`` (the C ``_queue`` module of 3.11 and 3.12, whose wait
is on a lock) can block until the next ``put`` instead of for ``t``. Its loop first tries the
queue's lock without waiting; when the lock is free (it is after every item taken, or after a
``put``) that try succeeds, and the time left is computed again from the deadline. A thread
held up between the two for longer than the time left (an interrupt, or preempted on a busy
machine) gets a negative time left, and the lock is then taken with it; for a lock a negative
timeout means *wait forever*. So the wait ends only at the next ``put``. Measured on the 2-core
development machine (``SimpleQueue.get(timeout=2e-6)`` on an empty queue whose lock was free,
watched by a thread that puts after 50 ms without progress): 5 of 54,270 calls blocked until
that put on an idle machine, 2 of 104,511 beside two busy processes on one core. A swarm on two
cores held the orchestrator's manager that way from near the run's end on (its events queue:
nothing was put any more), and every periodic wait of an agent could lose a tick or more.
CPython 3.13 rewrote the wait (a parking lot that checks for a passed deadline).

:func:`get_within` takes an item without waiting first. On an empty queue that leaves the
queue's lock taken by the caller, so the timed ``get`` that follows starts with a lock it
cannot take at once and waits on it for the full timeout; a ``put`` releases it with an item in
the queue, so the loop never goes round to the negative time left. It needs one consumer per
queue (the other waits would take that lock), as every queue of the project has.
``queue.Queue`` has no such flaw (its timed wait is Python code on a
:class:`threading.Condition`), but it is not safe to put into from a signal handler, which the
agents' and the manager's queues are, and costs more (a put and a get with an item there:
2.1-2.5 µs against 0.25 µs, one thread, on the development machine).
"""

from __future__ import annotations

import queue
from typing import TypeVar

T = TypeVar("T")


def get_within(fifo: queue.SimpleQueue[T], timeout_s: float) -> T:
    """The next item of ``fifo``, waiting at most ``timeout_s`` [s] for one.

    Args:
        fifo: a queue with one consumer (the calling thread).
        timeout_s: the longest wait [s]; 0 or less takes an item only if one is there.

    Raises:
        queue.Empty: no item came within ``timeout_s``.
    """
    try:
        return fifo.get_nowait()  # on an empty queue: its lock stays taken (module docstring)
    except queue.Empty:
        if not timeout_s > 0.0:  # NaN too
            raise
    return fifo.get(timeout=timeout_s)
