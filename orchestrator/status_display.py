"""Live status of a running experiment: one refreshed line on a terminal, log lines otherwise.

On a TTY the display rewrites one line in place (tick, rate, states, late ticks, lost agents)
at most a few times per second. When the output is not a terminal (CI, a pipe, a log file) it
writes a plain line every ``log_period_s`` seconds instead, so logs stay readable.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO


@dataclass(frozen=True)
class StatusSnapshot:
    """What the display shows.

    Attributes:
        experiment: experiment name.
        mode: ``lockstep`` or ``realtime``.
        k: current tick.
        n_ticks: ticks planned.
        tick_rate_hz: ticks per wall-clock second so far.
        late_ticks: ticks not complete by their deadline (realtime).
        states: lifecycle state by agent name (as last reported).
        lost: lost agents.
        paused: ticking is paused.
    """

    experiment: str
    mode: str
    k: int
    n_ticks: int
    tick_rate_hz: float
    late_ticks: int = 0
    states: dict[str, str] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)
    paused: bool = False

    def line(self) -> str:
        """One human line."""
        counts = Counter(self.states.values())
        states = " ".join(f"{state}:{n}" for state, n in sorted(counts.items())) or "-"
        text = (
            f"{self.experiment} [{self.mode}{' PAUSED' if self.paused else ''}] "
            f"tick {self.k}/{self.n_ticks} {self.tick_rate_hz:7.1f} Hz | agents {states} "
            f"| late ticks {self.late_ticks}"
        )
        if self.lost:
            text += f" | lost: {', '.join(self.lost)}"
        return text


class StatusDisplay:
    """Shows :class:`StatusSnapshot` updates on ``stream``.

    Args:
        stream: where to write (usually ``sys.stdout``).
        is_tty: rewrite one line in place (``None``: ask ``stream.isatty()``).
        log_period_s: period of the plain lines when not a TTY [s].
        clock: monotonic clock [s].
    """

    def __init__(
        self,
        stream: TextIO,
        *,
        is_tty: bool | None = None,
        log_period_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream = stream
        self.is_tty = stream.isatty() if is_tty is None else is_tty
        self.log_period_s = log_period_s
        self._clock = clock
        self._last_log = -float("inf")
        self._line_open = False
        self._width = 0

    def update(self, snapshot: StatusSnapshot) -> None:
        """Show the latest state (throttled when not a TTY)."""
        line = snapshot.line()
        if self.is_tty:
            padding = " " * max(0, self._width - len(line))
            self.stream.write("\r" + line + padding)
            self.stream.flush()
            self._width = len(line)
            self._line_open = True
            return
        now = self._clock()
        if now - self._last_log >= self.log_period_s:
            self._last_log = now
            self.stream.write(line + "\n")
            self.stream.flush()

    def log(self, message: str) -> None:
        """Write an event line (agent ready, agent lost ...) above the live line."""
        self.finish()
        self.stream.write(message + "\n")
        self.stream.flush()

    def finish(self) -> None:
        """End the live line (call before printing anything else)."""
        if self._line_open:
            self.stream.write("\n")
            self.stream.flush()
            self._line_open = False
            self._width = 0
