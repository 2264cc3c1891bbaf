"""The instance manager's ticks in flight, and the account of a closed tick.

Shared by the manager's bus callbacks (which store each agent's answer) and its ticking thread
(which releases and closes ticks); every access is under the manager's lock.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

#: Closed ticks remembered for answers that come after their tick was closed [ticks].
CLOSED_KEPT = 64


class TickAccount(NamedTuple):
    """A closed tick: index, scheduled/sent/done times [s, manager clock], late agents, and
    per agent its answer time after the send [s] (NaN: none; ``None``: not recorded)."""

    k: int
    scheduled: float
    sent: float
    done: float
    late: list[int]
    answers: np.ndarray | None


class TickWindow:
    """The ticks in flight, shared by the bus callbacks and the ticking thread (under a lock).

    Ticks ``base .. released`` are open (sent, not every answer in); at most ``window`` of
    them (realtime: one). Arrays are indexed ``[k % window, agent]`` and preallocated:
    recording an answer is a few element stores.
    """

    def __init__(self, n: int, window: int) -> None:
        self.window = window
        self.base = 0  # oldest open tick
        self.released = -1  # newest tick sent
        self.last_progress = 0.0
        self.expected = n
        self.count = np.zeros(window, dtype=np.int64)
        self.scheduled = np.zeros(window)
        self.sent = np.zeros(window)
        self.arrived = np.zeros((window, n), dtype=bool)
        self.answered_at = np.full((window, n), np.nan)  # manager clock [s]
        self.lost = np.zeros(n, dtype=bool)
        # The last CLOSED_KEPT closed ticks, by k % CLOSED_KEPT: k, send time, and the agents
        # whose answer was not in when it closed (cleared when it comes: once per agent).
        self._closed_k = np.full(CLOSED_KEPT, -1, dtype=np.int64)
        self._closed_sent = np.zeros(CLOSED_KEPT)
        self._closed_waiting = np.zeros((CLOSED_KEPT, n), dtype=bool)

    @property
    def k(self) -> int:
        """The newest tick sent (-1 before the first)."""
        return self.released

    def release(self, k: int, scheduled: float, sent: float) -> None:
        """Tick ``k`` (``released + 1``), scheduled at ``scheduled``, is sent at ``sent`` [s]."""
        slot = k % self.window
        self.released = k
        self.scheduled[slot], self.sent[slot] = scheduled, sent
        self.last_progress = max(self.last_progress, sent)
        self.count[slot] = 0
        self.arrived[slot] = False
        self.answered_at[slot] = np.nan

    def close_base(self) -> None:
        """Close the oldest open tick; remember its send time and who had not answered."""
        k, slot, at = self.base, self.base % self.window, self.base % CLOSED_KEPT
        self._closed_k[at], self._closed_sent[at] = k, self.sent[slot]
        np.logical_not(self.arrived[slot] | self.lost, out=self._closed_waiting[at])
        self.base = k + 1

    def late_answer(self, k: int, i: int, received: float) -> float | None:
        """Agent ``i``'s y of tick ``k``, closed without it, came at ``received`` [s, manager
        clock]: its answer time after the tick's send [s]. ``None`` when tick ``k`` is not
        among the last :data:`CLOSED_KEPT` closed ones, or agent ``i``'s answer was in when
        it closed or has come since (a duplicate)."""
        at = k % CLOSED_KEPT
        if not 0 <= k < self.base or self._closed_k[at] != k or not self._closed_waiting[at, i]:
            return None
        self._closed_waiting[at, i] = False
        return received - float(self._closed_sent[at])

    def base_complete(self) -> bool:
        """Every expected answer of the oldest open tick is in."""
        return self.base <= self.released and self.count[self.base % self.window] >= self.expected

    def unanswered(self) -> list[int]:
        """Agents (not lost) whose y of the oldest open tick is not in."""
        return self.late_at(math.inf)

    def late_at(self, deadline: float) -> list[int]:
        """Agents (not lost) whose y of the oldest open tick was not in at ``deadline`` [s,
        manager clock]: not arrived, or arrived after it (stamped when the manager got it)."""
        slot = self.base % self.window
        in_time = self.arrived[slot] & (self.answered_at[slot] <= deadline)
        return np.flatnonzero(~(in_time | self.lost)).tolist()

    def recount(self) -> None:
        """Recompute what is expected after agents were lost."""
        self.expected = int((~self.lost).sum())
        self.count[:] = (self.arrived & ~self.lost).sum(axis=1)
