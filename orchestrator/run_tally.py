"""The run's outcome as it comes in: ticks counted on time or late, and the agents' reports.

:class:`RunTally` keeps the instance manager's
:class:`~hilswarm.orchestrator.run_summary.RunSummary` up to date from two sources: each closed
tick's account (on the ticking thread: on time or late, per agent; its completion time; the
overload warning when many ticks in a row are late, with how busy the machine's CPUs were) and
each agent's status message (on a bus thread, under the manager's lock: the first safe entry,
degradations, the counters the agent reports). The summary then gives the run's outcome
(:mod:`hilswarm.orchestrator.outcome`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from hilswarm.orchestrator.machine_cpu import busy_fraction
from hilswarm.orchestrator.outcome import COUNTER_NAMES
from hilswarm.orchestrator.run_summary import AgentEvent, RunSummary

logger = logging.getLogger(__name__)

#: Realtime: ticks per block in which late ticks are counted for the overload warning.
OVERLOAD_BLOCK_TICKS = 100
#: Realtime: the overload warning is given when more than this fraction of a block was late.
OVERLOAD_LATE_FRACTION = 0.1
#: From this busy share of the machine's CPUs over a late block, the warning blames the CPUs;
#: below it, a slow agent or link (the CPUs had time to spare).
CPU_FULL_FRACTION = 0.75

#: Reads the machine's ``(busy, total)`` CPU time [s] (``None``: not available).
CpuTimes = Callable[[], tuple[float, float] | None]


def _cause(first: tuple[float, float] | None, last: tuple[float, float] | None) -> str:
    """The likely cause of a late block, from the CPUs' busy share over it (if known)."""
    busy = busy_fraction(first, last) if first is not None and last is not None else math.nan
    if math.isnan(busy):
        return "too many agents for the CPU cores, or slow links"
    if busy >= CPU_FULL_FRACTION:
        return f"the CPUs were {100 * busy:.0f} % busy over those ticks: too many agents for them"
    return (
        f"the CPUs were only {100 * busy:.0f} % busy over those ticks: more likely a slow "
        "agent, controller or link than too few cores"
    )


def counts(value: Any) -> int | dict[str, int] | None:
    """An agent's counter as reported (a count, or counts by key); ``None``: not a counter."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, dict):
        return {
            str(key): count
            for key, count in value.items()
            if isinstance(count, int) and not isinstance(count, bool)
        }
    return None


class RunTally:
    """Counts a run's ticks and keeps what the agents report, into ``summary``.

    Args:
        summary: the run's summary (its ``late`` holds every agent at 0).
        names: the experiment's agents, in order (late agents come as indices).
        n_ticks: the experiment's planned ticks.
        rate_hz: the tick rate [Hz], for the overload warning's text.
        say: where the overload warning also goes (the status display's log; ``None``: only
            the log).
        cpu_times: reads the machine's busy and total CPU time
            (:func:`~hilswarm.orchestrator.machine_cpu.read_cpu_times`), at the first tick of
            each block of :data:`OVERLOAD_BLOCK_TICKS` ticks and at the last of a late one, so
            that the warning can say how busy the CPUs were over it (``None``: it does not say).
    """

    def __init__(
        self,
        summary: RunSummary,
        names: Sequence[str],
        n_ticks: int,
        rate_hz: float,
        *,
        say: Callable[[str], None] | None = None,
        cpu_times: CpuTimes | None = None,
    ) -> None:
        self.summary = summary
        self.names = tuple(names)
        self.rate_hz = rate_hz
        self._say = say
        #: Per tick: completion after its scheduled time [s] (NaN: not complete, or late).
        self.completion = np.full(max(n_ticks, 1), np.nan)
        self._late_in_block = 0
        self._overload_reported = False
        self._cpu_times = cpu_times
        #: The machine's CPU times when the current block began (read at its first tick).
        self._block_cpu: tuple[float, float] | None = None

    def completed(self, k: int, completion_s: float) -> None:
        """Tick ``k`` was closed ``completion_s`` after its scheduled time [s] (NaN: not all
        answers came)."""
        if k < self.completion.size:
            self.completion[k] = completion_s

    def count(self, k: int, late: Sequence[int]) -> None:
        """Count closed tick ``k``: on time, or late for the agents ``late`` (indices)."""
        summary = self.summary
        for j in late:
            summary.late[self.names[j]] += 1
        if late:
            summary.note_late_tick(k)
            if k < self.completion.size:  # complete but late: the summary's percentiles
                self.completion[k] = math.nan  # count it as infinite
        else:
            summary.ticks += 1
        self._watch_overload(k, bool(late))

    def completion_s(self) -> list[float]:
        """The completion times of the ticks run that were on time [s]."""
        accounted = self.completion[: self.summary.ticks_run]
        return accounted[np.isfinite(accounted)].tolist()

    def _watch_overload(self, k: int, late: bool) -> None:
        """Say once when many recent ticks were late: the machine may not keep up."""
        if self._overload_reported:
            return
        if k % OVERLOAD_BLOCK_TICKS == 0 and self._cpu_times is not None:
            self._block_cpu = self._cpu_times()
        self._late_in_block += late
        if (k + 1) % OVERLOAD_BLOCK_TICKS:
            return
        late_count, self._late_in_block = self._late_in_block, 0
        if late_count > OVERLOAD_LATE_FRACTION * OVERLOAD_BLOCK_TICKS:
            self._overload_reported = True
            first, times = self._block_cpu, self._cpu_times
            last = times() if first is not None and times is not None else None
            message = (
                f"{late_count} of ticks {k + 1 - OVERLOAD_BLOCK_TICKS}..{k} were late: the agents "
                f"do not keep up with {self.rate_hz:g} Hz here ({_cause(first, last)})"
                "; see docs/running.md, Performance"
            )
            logger.warning("%s", message)
            if self._say is not None:
                self._say(message)

    def note_status(
        self, name: str, state: str, message: dict[str, Any], *, stopping: bool
    ) -> None:
        """Keep what the outcome needs from agent ``name``'s status ``message`` (its ``state``);
        ``stopping``: the run is stopping, so a safe state is the stop's, not a fault."""
        summary = self.summary
        try:
            k = int(message.get("k", 0))
        except (TypeError, ValueError):
            k = 0
        detail = str(message.get("detail", ""))
        if state == "safe" and name not in summary.safe and not stopping:
            summary.safe[name] = AgentEvent(k, detail)
        elif state == "degraded" and message.get("kind", "transition") == "transition":
            summary.degraded.setdefault(name, []).append(AgentEvent(k, detail))
        kept = {
            key: value
            for key in COUNTER_NAMES
            if key in message and (value := counts(message[key])) is not None
        }
        if kept:  # the agent's totals so far: the latest status holds them all
            summary.counters.setdefault(name, {}).update(kept)
