"""What one run did: ticks, wall time, speed, completion times, and every degradation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class AgentEvent:
    """An agent's state change the outcome depends on (safe mode, loss, degraded link).

    Attributes:
        tick: the tick at which it happened (the agent's own tick for its reports).
        detail: the reason, as reported.
    """

    tick: int
    detail: str = ""


@dataclass
class RecordingReport:
    """What happened to the recording of a run (filled in by the recorder's owner).

    Attributes:
        segments: the files of the recording, in order (``run.mcap``, ``run.1.mcap``, ...).
        failures: one line per failure of the recorder process (died, disk full), with the
            tick it happened at.
        lost_records: manager records (messages of the bus) that never reached a file.
        lost_ticks: ``(first, last)`` tick range of the lost records (``None``: none lost).
        stopped_at_tick: the recording ended early at this tick (disk full, policy
            ``continue``; ``None``: it covers the whole run).
    """

    segments: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    lost_records: int = 0
    lost_ticks: tuple[int, int] | None = None
    stopped_at_tick: int | None = None

    @property
    def complete(self) -> bool:
        """True when every record of the run is in the files."""
        return not self.lost_records and self.stopped_at_tick is None


@dataclass
class RunSummary:
    """What happened in one run.

    Attributes:
        experiment: experiment name.
        mode: ``lockstep`` or ``realtime``.
        ticks: ticks completed on time (every live agent answered; realtime: before the next
            tick was due); the late ones are :attr:`late_ticks`.
        planned_ticks: ticks the experiment asked for.
        wall_s: wall-clock length of the ticking phase [s].
        stop_reason: why the run ended (``"completed"``, ``"interrupted"``, ...).
        lost: agents lost (killed, hung), in order of loss.
        lost_at: per lost agent, the tick of the loss and its reason.
        safe: per agent, its first entry into safe mode (tick and reason).
        degraded: per agent, its entries into the ``degraded`` state (link fault).
        counters: per agent, the latest counters its status reports (``malformed`` and
            ``dropped`` messages by key or reason, ``skipped`` ticks, ``link_faults``,
            ``stale_samples``).
        late: late answers per agent (realtime).
        late_ticks: ticks not complete by the next tick's deadline (realtime).
        first_late_tick, last_late_tick: the first and the last of them (``None``: none), so
            a reader tells a start-up transient (late ticks only at the start) from an
            overload that lasts.
        max_late_fraction: late ticks above this fraction of the planned ticks degrade the
            outcome.
        completion_s: per tick, completion time after its scheduled time [s].
        estop_tick: the tick of a swarm-wide e-stop (``None``: none).
        failed: True when the run could not do what was asked (lost agent with policy stop,
            start-up failure).
        recording: what happened to the recording (``None``: not recorded).
        dt_s: the tick period [s].
    """

    experiment: str
    mode: str
    ticks: int = 0
    planned_ticks: int = 0
    wall_s: float = 0.0
    stop_reason: str = ""
    lost: list[str] = field(default_factory=list)
    lost_at: dict[str, AgentEvent] = field(default_factory=dict)
    safe: dict[str, AgentEvent] = field(default_factory=dict)
    degraded: dict[str, list[AgentEvent]] = field(default_factory=dict)
    counters: dict[str, dict[str, int | dict[str, int]]] = field(default_factory=dict)
    late: dict[str, int] = field(default_factory=dict)
    late_ticks: int = 0
    first_late_tick: int | None = None
    last_late_tick: int | None = None
    max_late_fraction: float = 0.01
    completion_s: list[float] = field(default_factory=list)
    estop_tick: int | None = None
    failed: bool = False
    recording: RecordingReport | None = None
    dt_s: float = 0.0

    def note_late_tick(self, k: int) -> None:
        """Count tick ``k`` as late (ticks are closed in order)."""
        self.late_ticks += 1
        if self.first_late_tick is None:
            self.first_late_tick = k
        self.last_late_tick = k

    def late_range(self) -> str:
        """Where the late ticks were: ``"at tick 4"``, ``"between ticks 0 and 2"`` (the first and
        the last; not every tick between was late), or ``""`` for none."""
        first, last = self.first_late_tick, self.last_late_tick
        if first is None or last is None:
            return ""
        return f"at tick {first}" if first == last else f"between ticks {first} and {last}"

    @property
    def ticks_run(self) -> int:
        """Ticks accounted, on time or late."""
        return self.ticks + self.late_ticks

    @property
    def speed(self) -> float:
        """Experiment time per wall-clock time (lockstep speed-up; ~1 in realtime, late ticks
        included: they ran)."""
        return 0.0 if self.wall_s <= 0 else self.ticks_run * self.dt_s / self.wall_s

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
        """A few human lines (the degradations are listed by :mod:`.outcome`)."""
        p50, p99 = self.completion_percentiles()
        lines = [
            f"experiment {self.experiment!r} ({self.mode}): {self.ticks_run}/{self.planned_ticks} "
            f"ticks{f' ({self.late_ticks} late)' if self.late_ticks else ''} in "
            f"{self.wall_s:.2f} s wall clock ({self.speed:.1f}x real time); "
            f"stopped: {self.stop_reason}",
            f"tick completion p50 {_ms(p50)}, p99 {_ms(p99)}; late ticks {self.late_ticks}"
            + (f" ({self.late_range()})" if self.late_ticks else ""),
        ]
        return "\n".join(lines)


def _ms(seconds: float) -> str:
    """``1.23 ms``, or ``late`` for an infinite completion time."""
    return "late" if math.isinf(seconds) else f"{seconds * 1e3:.2f} ms"
