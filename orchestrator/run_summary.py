"""What one run did: ticks, wall time, speed, completion times, late and lost agents."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class RunSummary:
    """What happened in one run.

    Attributes:
        experiment: experiment name.
        mode: ``lockstep`` or ``realtime``.
        ticks: ticks completed (every live agent answered).
        planned_ticks: ticks the experiment asked for.
        wall_s: wall-clock length of the ticking phase [s].
        stop_reason: why the run ended (``"completed"``, ``"interrupted"``, ...).
        lost: agents lost (killed, hung), in order of loss.
        late: late answers per agent (realtime).
        late_ticks: ticks not complete by the next tick's deadline (realtime).
        completion_s: per tick, completion time after its scheduled time [s].
        failed: True when the run could not do what was asked (lost agent with policy stop,
            start-up failure).
    """

    experiment: str
    mode: str
    ticks: int = 0
    planned_ticks: int = 0
    wall_s: float = 0.0
    stop_reason: str = ""
    lost: list[str] = field(default_factory=list)
    late: dict[str, int] = field(default_factory=dict)
    late_ticks: int = 0
    completion_s: list[float] = field(default_factory=list)
    failed: bool = False

    @property
    def speed(self) -> float:
        """Experiment time per wall-clock time (lockstep speed-up; ~1 in realtime)."""
        return 0.0 if self.wall_s <= 0 else self.ticks * self._dt / self.wall_s

    _dt: float = 0.0

    def completion_percentiles(self) -> tuple[float, float]:
        """(p50, p99) of tick completion times [s] over every tick that was due.

        A late tick (not complete when the next one was due) counts as ``inf``: when more than
        1 % of the ticks were late, p99 is ``inf`` (NaN when no tick was accounted).
        """
        if not self.completion_s and not self.late_ticks:
            return math.nan, math.nan
        values = np.concatenate([np.asarray(self.completion_s), np.full(self.late_ticks, np.inf)])
        p50, p99 = np.percentile(values, [50, 99], method="inverted_cdf")
        return float(p50), float(p99)

    def text(self) -> str:
        """A few human lines."""
        p50, p99 = self.completion_percentiles()
        lines = [
            f"experiment {self.experiment!r} ({self.mode}): {self.ticks}/{self.planned_ticks} "
            f"ticks in {self.wall_s:.2f} s wall clock ({self.speed:.1f}x real time); "
            f"stopped: {self.stop_reason}",
            f"tick completion p50 {_ms(p50)}, p99 {_ms(p99)}; late ticks {self.late_ticks}",
        ]
        late = {name: n for name, n in self.late.items() if n}
        if late:
            lines.append("late answers: " + ", ".join(f"{n}={c}" for n, c in late.items()))
        if self.lost:
            lines.append("lost agents: " + ", ".join(self.lost))
        return "\n".join(lines)


def _ms(seconds: float) -> str:
    """``1.23 ms``, or ``late`` for an infinite completion time."""
    return "late" if math.isinf(seconds) else f"{seconds * 1e3:.2f} ms"
