"""The agent's tick engine: which tick runs when, and with which neighbour outputs.

Pure scheduling logic, no bus and no clock: the agent's bus adapter
(:mod:`hilswarm.agents.agent`) decodes messages and hands them here with the time they arrived
(``arrived`` [s], the agent's monotonic clock); its worker thread asks :meth:`TickEngine.take`
for the next tick to run. Not thread-safe: the agent serialises calls with one lock, held only
for these short calls (never around board I/O or the controller).

Contract (``k``: tick index; ``window``: the experiment's ``lockstep_window`` [ticks]):

* **Release horizon.** A tick message of the instance manager releases every tick up to its
  ``k``. Lockstep: the agent steps through every released tick. Realtime: the agent runs the
  newest released tick; ticks it fell behind on are *skipped* (reported with the next answer).
* **Lockstep window.** The manager releases at most ``window`` ticks past the slowest agent's
  last answer, so a genuine tick message never carries ``k > taken + window`` (``taken``: the
  last tick this agent started). Anything further is rejected (``dropped["tick_ahead"]``): a
  lockstep agent never runs more than ``window`` ticks ahead of its own last tick, whatever
  arrives.
* **Realtime rate.** Genuine realtime tick messages come one per period: a tick that claims
  more periods than elapsed (on the agent's clock) since the newest accepted one was due,
  plus :data:`REALTIME_SLACK_TICKS`, is rejected (``tick_ahead``), so a forged far-future
  tick cannot freeze the schedule; a run's first tick must lie within the window. A tick
  message more than :data:`STALE_TICK_PERIODS` late that arrives right behind the previous
  one (it queued up while the agent was stalled) is counted ``stale`` (normal under load);
  it is still released, and since the worker takes only the newest released tick, a burst
  of queued ticks runs once.
* **The past and other runs.** A tick below the horizon (``tick_past``), a tick whose ``t`` is
  not ``k * dt`` (``tick_time``), a tick in the other mode than the run's first tick
  (``tick_mode``) and a lost-agent index outside the experiment (``tick_missing``) are
  rejected. (Messages of another run never reach an agent: the run id is part of the bus keys.)
* **Neighbour history.** Neighbour outputs ``y_j`` are kept per neighbour from
  ``taken - NEIGHBOUR_HISTORY`` on (a neighbour may run up to ``window`` ahead; a realtime
  catch-up may use older ones), at most :data:`MAX_NEIGHBOUR_HISTORY` each. Outputs for ticks
  not released yet (beyond the window) are rejected (``y_ahead``), a second output for the
  same tick is rejected (``y_duplicate``), and so is an output whose size differs from that
  neighbour's first (``y_size``); outputs too old to be used are ignored.
* **Gather.** Tick ``k`` (``k > 0``, the agent actuating) uses each neighbour's ``y_{k-1}``;
  a neighbour the manager reports missing counts as no data (``None``). Lockstep waits until
  every other neighbour's ``y_{k-1}`` is in. Realtime after skipped ticks may use the newest
  older output of a neighbour.
* **Wake.** :meth:`TickEngine.on_tick` and :meth:`TickEngine.on_neighbour` return ``True``
  when the worker should look for a tick to run: an accepted tick message, or the last input
  a released tick waits for (not each neighbour's: a worker woken by the first of two outputs
  would find the tick still waiting and sleep again). Whatever the order of arrival, a tick
  that becomes runnable always comes with such a ``True``.

* **Self-clocked realtime** (the manager sends a schedule instead of tick messages, see
  :class:`~hilswarm.agents.bus.ScheduleMessage`). Tick ``j`` (``first <= j <= last``) is due at
  ``t0 + j * dt``; :meth:`TickEngine.take` is given the time (``now``) and hands out the newest
  due tick (the ticks in between are skipped, as above); :meth:`TickEngine.next_due` says when
  the next one is due, so the worker waits for that deadline. The run's mode is fixed by its
  first message: a schedule in a run of tick messages, or a tick message in a self-clocked
  run, is rejected (``tick_mode``). A schedule is accepted only if its ``dt`` is the
  experiment's (``schedule_dt``) and its anchor is plausible (``schedule_time``): the next
  tick it makes due lies at most :data:`SCHEDULE_AHEAD_PERIODS` ahead (so it cannot freeze the
  agent), and the tick due when it arrived lies no further ahead than the periods elapsed
  since this agent's newest tick was due, plus :data:`REALTIME_SLACK_TICKS` (the run's first
  schedule: its ``first`` within the window, and the tick due at arrival at most
  :data:`SCHEDULE_START_LAG_PERIODS` past ``first``), so it cannot race the agent ahead of the
  schedule. A schedule with the anchor in force (same ``t0`` and ``first``) only changes
  ``last`` (a pause) and the lost agents. **No wait for inputs:** a self-clocked tick runs at
  its due time with the neighbours' ``y_{k-1}`` that are in; one that is not counts as no
  data (``None``) and is noted in :attr:`TickEngine.inputs_missing` (unless the manager
  reported that neighbour lost), which the agent publishes, so the record says which inputs
  each tick used. With a *phase* (``phase_s``, under one period: ``[mocap]
  tick_spread_frames``) this agent's tick ``j`` is due ``phase_s`` after the swarm's due time
  for ``j``; the schedule's checks above stay on the swarm's times.

Counters (:attr:`TickEngine.dropped`, :attr:`TickEngine.stale`) only grow; the agent adds the
malformed-message counts of its decoders and publishes both in its status messages.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

#: Realtime: a tick message later than this many periods after its schedule is skipped.
STALE_TICK_PERIODS = 1.5
#: Realtime: how fast the estimate of the bus delay forgets its minimum [periods per tick].
DELAY_ESTIMATE_RELAX = 0.01
#: Realtime: ticks a message may run ahead of the periods elapsed since the newest one [ticks].
REALTIME_SLACK_TICKS = 2.0
#: Neighbour outputs kept per neighbour older than this agent's last tick [ticks].
NEIGHBOUR_HISTORY = 4
#: Bound on the neighbour outputs kept per neighbour (newer ones included) [ticks].
MAX_NEIGHBOUR_HISTORY = 2048
#: Realtime: neighbour outputs accepted past the newest released tick [ticks] (a neighbour's
#: answer may overtake the tick message on its way to this agent).
REALTIME_Y_AHEAD = 2
#: Relative tolerance of a tick's ``t`` against ``k * dt`` (and of a schedule's ``dt``).
TICK_TIME_RTOL = 1e-9
#: Realtime: the manager's lead before tick 0 is this many periods, at most
#: :data:`START_LEAD_MAX_S` (plus the pre-roll's span when self-clocked, :func:`start_lead`).
START_LEAD_PERIODS = 5
#: Realtime: bound on the lead before tick 0, without the pre-roll [s].
START_LEAD_MAX_S = 0.05
#: Self-clocked: warm-up outputs each agent puts on its y key before tick 0 (the pre-roll,
#: :func:`preroll_times`).
PREROLL_TICKS = 8
#: Self-clocked: longest spacing of the pre-roll's warm-up outputs [s] (the period itself when
#: shorter).
PREROLL_PERIOD_MAX_S = 0.01
#: Self-clocked: a schedule may make its next tick due at most this far ahead [periods]: the
#: manager's first tick is due at most :data:`START_LEAD_PERIODS` + :data:`PREROLL_TICKS`
#: periods after its schedule (:func:`start_lead`), and 5 more are slack.
SCHEDULE_AHEAD_PERIODS = float(START_LEAD_PERIODS + PREROLL_TICKS + 5)
#: Self-clocked: the run's first schedule may arrive this late [periods after ``first`` was
#: due] (an agent stalled at the start joins at the tick due then).
SCHEDULE_START_LAG_PERIODS = 100.0


def start_lead(dt: float, *, self_clocked: bool) -> float:
    """The manager's lead before tick 0 of a realtime run [s]: :data:`START_LEAD_PERIODS`
    periods, at most :data:`START_LEAD_MAX_S`, and for a self-clocked run the pre-roll's span
    (:func:`preroll_times`) before that."""
    lead = min(START_LEAD_MAX_S, START_LEAD_PERIODS * dt)
    if self_clocked:
        lead += PREROLL_TICKS * min(dt, PREROLL_PERIOD_MAX_S)
    return lead


def preroll_times(t0: float, dt: float) -> list[float]:
    """When a self-clocked agent puts its warm-up outputs before tick 0 (due at ``t0`` [s,
    CLOCK_MONOTONIC], period ``dt`` [s]): :data:`PREROLL_TICKS` instants spaced by the period
    (at most :data:`PREROLL_PERIOD_MAX_S`), the last one a spacing before ``t0``, oldest first.

    The pre-roll (docs/running.md, "The pre-roll"): a run's processes sit idle between arming
    and tick 0, and their first ticks, all at once, were measured to cost up to twice a steady
    tick (the bare bus, 32 clients at 100 Hz: tick 0 complete after 6.1-9.3 ms, against
    3.3-4.7 ms with ten warm-up exchanges before it). So in the lead before tick 0 every agent
    runs the tick path's bus half: its worker wakes on the schedule and puts an output with
    ``k < 0`` (NaN values) on its y key, which its neighbours and the manager receive and
    ignore (:func:`is_warmup`). No controller step, no board exchange: nothing the experiment
    sees, and nothing recorded.
    """
    spacing = min(dt, PREROLL_PERIOD_MAX_S)
    return [t0 - j * spacing for j in range(PREROLL_TICKS, 0, -1)]


def is_warmup(k: int) -> bool:
    """Is an output of tick ``k`` a pre-roll warm-up (``k < 0``), which every receiver ignores?"""
    return k < 0


#: Reasons a well-formed input is rejected (keys of :attr:`TickEngine.dropped`).
DROP_REASONS = (
    "tick_ahead",
    "tick_past",
    "tick_time",
    "tick_mode",
    "tick_missing",
    "y_ahead",
    "y_duplicate",
    "y_size",
    "schedule_dt",
    "schedule_time",
)

_NOBODY: frozenset[str] = frozenset()


class Tick(NamedTuple):
    """A tick to run now.

    Attributes:
        k: tick index.
        t: experiment time of the tick [s].
        skipped: ticks dropped before this one because the agent fell behind (realtime).
        neighbours: each neighbour's ``y_{k-1}`` (``None``: no data), or ``None`` when the
            tick gathers nothing (tick 0, or not actuating).
        due: self-clocked: when this agent's tick was due [s, the agent's monotonic clock],
            its phase included; NaN for a tick message's tick.
    """

    k: int
    t: float
    skipped: int
    neighbours: dict[str, np.ndarray | None] | None
    due: float = math.nan


class TickEngine:
    """Scheduling state of one agent (see the module docstring).

    Args:
        neighbours: names of the agents whose outputs this agent uses.
        agent_names: every agent of the experiment in graph order (tick messages name lost
            agents by index).
        dt: control period [s].
        window: the experiment's lockstep window [ticks] (>= 1).
        phase_s: self-clocked: this agent ticks this long after the swarm's due times [s]
            (0 <= phase_s < dt; ``[mocap] tick_spread_frames``).
    """

    def __init__(
        self,
        neighbours: Sequence[str],
        agent_names: Sequence[str],
        dt: float,
        window: int,
        *,
        phase_s: float = 0.0,
    ) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0 [s], got {dt!r}")
        if not (isinstance(window, int) and window >= 1):
            raise ValueError(f"window must be an integer >= 1 [ticks], got {window!r}")
        if not (math.isfinite(phase_s) and 0.0 <= phase_s < dt):
            raise ValueError(f"phase_s must be in [0, dt) [s], got {phase_s!r}")
        #: Self-clocked: this agent's ticks are due this long after the swarm's [s].
        self.phase_s = float(phase_s)
        self.neighbours = tuple(neighbours)
        self.agent_names = tuple(agent_names)
        self.dt = float(dt)
        self.window = window
        self.index = {name: i for i, name in enumerate(self.neighbours)}
        self.history: dict[str, dict[int, np.ndarray]] = {n: {} for n in self.neighbours}
        self.received_from: set[str] = set()
        self._sizes: dict[str, int] = {}  # each neighbour's output size, fixed by its first
        #: Last tick started (taken by :meth:`take`); -1 before tick 0.
        self.k = -1
        #: Highest tick released by the manager.
        self.horizon = -1
        self.horizon_t = 0.0
        #: ``True``/``False`` once the first tick fixed the run's mode.
        self.realtime: bool | None = None
        self.running = False  # ticks are handed out only while running
        self.dropped: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self.stale = 0
        self._tick_missing = _NOBODY  # realtime: missing for the newest tick
        self._lost = _NOBODY  # lockstep: agents the manager reports lost
        self._delay_estimate = math.inf  # realtime: tick arrival - schedule, minimum [s]
        self._last_arrival = -math.inf  # realtime: arrival of the previous tick message [s]
        self._horizon_arrival = -math.inf  # realtime: arrival of the newest accepted tick [s]
        self._late_alone = False  # realtime: the previous tick message was late on its own
        #: ``True`` once a schedule fixed the run as self-clocked, ``False`` once a tick
        #: message fixed it as driven by tick messages.
        self.clocked: bool | None = None
        self._t0 = math.nan  # self-clocked: tick j is due at t0 + j * dt [s]
        self._first = 0  # self-clocked: the schedule's first tick
        # self-clocked: the anchor before it (t0, first), which still times the ticks before
        # ``_first`` this agent has not run yet (a new anchor may arrive just before them)
        self._prev: tuple[float, int] | None = None
        self._last = -1  # self-clocked: its last tick (-1: no schedule)
        self._taken_due = math.nan  # self-clocked: when tick self.k was due [s]
        #: Self-clocked: per neighbour, the ticks that used no data for it although the
        #: manager had not reported it lost (drained by :meth:`take_inputs_missing`).
        self.inputs_missing: dict[str, list[int]] = {}

    # -- inputs ------------------------------------------------------------------------------

    def on_tick(
        self, k: int, t: float, missing: Sequence[int], realtime: bool, arrived: float
    ) -> bool:
        """A tick message releasing ticks up to ``k`` (at ``t`` [s]) arrived at ``arrived`` [s].

        Args:
            missing: indices (experiment order) of agents whose outputs are not coming.
            realtime: the manager's mode.
            arrived: arrival time [s, the agent's monotonic clock].

        Returns:
            ``True`` when it was accepted (a tick may be ready to run).
        """
        if self.clocked:
            self.dropped["tick_mode"] += 1
            return False
        if self.realtime is None:
            self.realtime = realtime
        elif realtime != self.realtime:
            self.dropped["tick_mode"] += 1
            return False
        self.clocked = False
        if k < 0 or abs(t - k * self.dt) > TICK_TIME_RTOL * max(1.0, abs(t)):
            self.dropped["tick_time"] += 1
            return False
        names = self.agent_names
        if missing:
            if max(missing) >= len(names):
                self.dropped["tick_missing"] += 1
                return False
            lost = frozenset(names[i] for i in missing)
        else:
            lost = _NOBODY
        if not realtime:
            if k > self.k + self.window:
                self.dropped["tick_ahead"] += 1
                return False
            if k < self.horizon:
                self.dropped["tick_past"] += 1
                return False
            if lost:
                self._lost = self._lost | lost
            self.horizon = k
            self.horizon_t = t
            return True
        if k <= self.horizon:
            self.dropped["tick_past"] += 1
            return False
        if self.horizon < 0:
            if k > self.window:  # the first tick of a run is 0
                self.dropped["tick_ahead"] += 1
                return False
        else:
            # The newest accepted tick was due (on this clock) at its schedule plus the
            # smallest bus delay seen, or earlier if it came earlier.
            due = min(self._horizon_arrival, self.horizon_t + self._delay_estimate)
            if k - self.horizon > (arrived - due) / self.dt + REALTIME_SLACK_TICKS:
                self.dropped["tick_ahead"] += 1
                return False
        if self._is_stale(t, arrived):
            # It queued up while this agent was stalled. Still released (the last tick of a
            # run may be one): the worker takes only the newest tick, so a burst runs once.
            self.stale += 1
        self.horizon, self.horizon_t, self._tick_missing = k, t, lost
        self._horizon_arrival = arrived
        return True

    def on_schedule(
        self,
        first: int,
        last: int,
        t0: float,
        dt: float,
        *,
        missing: Sequence[int] = (),
        arrived: float,
    ) -> bool:
        """A schedule of the manager arrived at ``arrived`` [s, the agent's monotonic clock].

        Args:
            first: its first tick; ``last``: its last tick.
            t0: when tick 0 would be due [s, CLOCK_MONOTONIC]; tick ``j`` at ``t0 + j * dt``.
            dt: its period [s] (must be the experiment's).
            missing: indices (experiment order) of agents the manager reports lost.

        Returns:
            ``True`` when it was accepted (the next tick's due time may have changed).
        """
        if self.realtime is False or self.clocked is False:
            self.dropped["tick_mode"] += 1
            return False
        period = self.dt
        if not (math.isfinite(dt) and abs(dt - period) <= TICK_TIME_RTOL * period):
            self.dropped["schedule_dt"] += 1
            return False
        if not math.isfinite(t0) or first < 0 or last < first:
            self.dropped["schedule_time"] += 1
            return False
        names = self.agent_names
        if missing and max(missing) >= len(names):
            self.dropped["tick_missing"] += 1
            return False
        if t0 != self._t0 or first != self._first:  # a new anchor: is it plausible?
            upcoming = max(first, self.k + 1)
            if upcoming <= last and t0 + upcoming * period - arrived > (
                SCHEDULE_AHEAD_PERIODS * period
            ):
                self.dropped["schedule_time"] += 1  # it would freeze the agent
                return False
            due_now = math.floor((arrived - t0) / period)  # the tick due at arrival
            if self.clocked is None:  # the run's first schedule
                too_far = first > self.window or due_now > first + SCHEDULE_START_LAG_PERIODS
            else:  # no further than the periods elapsed since its newest tick was due
                if self.k >= self._first:
                    ref_k, ref_due = self.k, self._taken_due
                else:  # none taken on this anchor yet: the tick before its first
                    ref_k = self._first - 1
                    ref_due = self._t0 + ref_k * period
                elapsed = max(0.0, (arrived - ref_due) / period)
                too_far = due_now > ref_k + elapsed + REALTIME_SLACK_TICKS
            if too_far:
                self.dropped["schedule_time"] += 1  # it would race the agent ahead
                return False
        if self.clocked and first > self._first and self.k + 1 < first:
            self._prev = (self._t0, self._first)  # ticks before ``first`` keep their times
        elif first <= self.k + 1:
            self._prev = None
        self.clocked = self.realtime = True
        self._t0, self._first, self._last = t0, first, last
        self._lost = frozenset(names[i] for i in missing) if missing else _NOBODY
        return True

    def next_due(self) -> float | None:
        """Self-clocked: when the next tick is due [s] (``None``: none is, or not running)."""
        if not (self.clocked and self.running):
            return None
        upcoming = self._upcoming()
        if upcoming > self._last:
            return None
        return self._due(upcoming) + self.phase_s

    @property
    def taken_due(self) -> float:
        """Self-clocked: when this agent's last tick taken was due [s], its phase included
        (NaN before the first)."""
        return self._taken_due + self.phase_s

    def _upcoming(self) -> int:
        """Self-clocked: the next tick this agent may run."""
        prev = self._prev
        if prev is not None and self.k + 1 < self._first:
            return max(prev[1], self.k + 1)
        return max(self._first, self.k + 1)

    def _due(self, k: int) -> float:
        """Self-clocked: when tick ``k`` is due [s] (before the anchor's first tick: on the
        anchor before it)."""
        prev = self._prev
        if prev is not None and k < self._first:
            return prev[0] + k * self.dt
        return self._t0 + k * self.dt

    def take_inputs_missing(self) -> dict[str, list[int]]:
        """The ticks that used no data for a neighbour since the last call (see
        :attr:`inputs_missing`), by neighbour; the record is emptied."""
        taken, self.inputs_missing = self.inputs_missing, {}
        return taken

    def _is_stale(self, t: float, arrived: float) -> bool:
        """Realtime: did the tick of time ``t`` [s] queue up while this agent was stalled?

        Its delay (arrival on this agent's clock minus ``t``) is compared with the smallest
        delay seen (which slowly forgets, so a slower bus is accepted). A message more than
        :data:`STALE_TICK_PERIODS` late that arrives right behind the previous one (a burst of
        queued messages) is stale. A late one on its own runs; two in a row mean the schedule
        moved (a resume) or the bus got slower, and the second becomes the new reference.
        """
        dt = self.dt
        delay = arrived - t
        burst = arrived - self._last_arrival < 0.5 * dt
        self._last_arrival = arrived
        if delay - self._delay_estimate > STALE_TICK_PERIODS * dt:
            if burst and self.k >= 0:
                return True
            if self._late_alone:
                self._delay_estimate = delay
            self._late_alone = True
            return False
        self._late_alone = False
        self._delay_estimate = min(delay, self._delay_estimate + DELAY_ESTIMATE_RELAX * dt)
        return False

    def on_neighbour(
        self, name: str, k: int, values: np.ndarray, arrived: float | None = None
    ) -> bool:
        """Neighbour ``name``'s output ``y_k`` arrived (at ``arrived`` [s], the agent's clock;
        used by a self-clocked run to bound how far ahead it may be).

        Returns:
            ``True`` when it was kept and brought in the last input the next released tick
            waits for (so the worker is woken once per tick, not once per neighbour).
        """
        history = self.history[name]
        size = self._sizes.get(name)
        if size is None:
            self._sizes[name] = values.shape[0]
        elif values.shape[0] != size:
            self.dropped["y_size"] += 1
            return False
        if self.clocked:  # at most a few ticks past the tick due (or this agent's own)
            due = self.k
            if arrived is not None and self._last >= 0:
                due = max(due, math.floor((arrived - self._t0) / self.dt))
            limit = due + REALTIME_Y_AHEAD
        elif self.realtime:
            limit = max(self.horizon, self.k) + REALTIME_Y_AHEAD
        else:  # tick k must have been released, which the window bounds
            limit = self.k + self.window + 1
        if k > limit:
            self.dropped["y_ahead"] += 1
            return False
        if k in history:
            self.dropped["y_duplicate"] += 1
            return False
        oldest_kept = self.k - NEIGHBOUR_HISTORY
        if k < oldest_kept:
            return False  # too old to be used: nothing to keep
        history[k] = values
        self.received_from.add(name)
        # Keep what a tick may still need: y_{self.k} and newer (a neighbour may run up to a
        # lockstep window ahead), and a few older ones for a realtime catch-up.
        while len(history) > 1:
            oldest = min(history)
            if oldest >= oldest_kept and len(history) <= MAX_NEIGHBOUR_HISTORY:
                break
            del history[oldest]
        if self.clocked:
            return False  # a self-clocked tick waits for its due time, not for inputs
        return self.running and self.horizon > self.k and self._completes(name, k)

    def _completes(self, name: str, k: int) -> bool:
        """Ticks released by messages: is ``y_k`` of neighbour ``name`` the input the next
        tick waits for, and every other neighbour's already in (or counted as no data)?

        Tick ``j`` waits for the neighbours' ``y_{j-1}`` alone (:meth:`take`); the next one is
        lockstep's ``self.k + 1`` and realtime's newest released, ``self.horizon`` (after
        skipped ticks that one takes older outputs and waits for nothing: it was ready when
        its tick message came).
        """
        if self.realtime:
            needed, lost = self.horizon - 1, self._tick_missing
        else:
            needed, lost = self.k, self._lost
        if k != needed:
            return False
        history = self.history
        return all(
            other == name or other in lost or needed in history[other] for other in self.neighbours
        )

    # -- running ticks -------------------------------------------------------------------------

    def take(self, *, gather: bool, now: float | None = None) -> Tick | None:
        """The next tick to run, or ``None`` while none is released or its inputs are not in.

        A returned tick is started: :attr:`k` becomes its index.

        Args:
            gather: the tick uses the neighbours' outputs (the agent is actuating and has
                sensed at least once); ignored for tick 0.
            now: the time [s, the agent's monotonic clock]; needed by a self-clocked run.
        """
        if self.clocked:
            return self._take_due(gather, now)
        if not self.running or self.k >= self.horizon:
            return None
        if self.realtime:  # the newest released tick; those in between are skipped
            k = self.horizon
            skipped = k - self.k - 1 if self.k >= 0 else 0
            missing, stale_ok, t = self._tick_missing, skipped > 0, self.horizon_t
        else:
            k, skipped, missing, stale_ok = self.k + 1, 0, self._lost, False
            t = k * self.dt
        neighbours = None
        if gather and k > 0:
            neighbours = self.gather(k - 1, missing, stale_ok)
            if neighbours is None:
                return None  # a neighbour's y_{k-1} is still on its way
        self.k = k
        return Tick(k, t, skipped, neighbours)

    def _take_due(self, gather: bool, now: float | None) -> Tick | None:
        """Self-clocked: the newest tick due at ``now``, with the inputs that are in."""
        if now is None:
            raise ValueError("a self-clocked tick engine needs the time: take(now=...)")
        due = self.next_due()
        if due is None or now < due:
            return None
        now -= self.phase_s  # on the swarm's times from here on
        upcoming, dt = self._upcoming(), self.dt
        if now >= self._t0 + max(upcoming, self._first) * dt:  # on the anchor in force
            k = max(upcoming, self._first, math.floor((now - self._t0) / dt))
        else:  # the ticks before its first, on the anchor before it
            prev_t0 = self._prev[0] if self._prev is not None else self._t0
            k = max(upcoming, min(self._first - 1, math.floor((now - prev_t0) / dt)))
        k = min(self._last, k)
        skipped = k - self.k - 1 if self.k >= 0 else 0
        neighbours = None
        if gather and k > 0:
            neighbours = self.gather(k - 1, self._lost, skipped > 0, wait=False)
            if neighbours is not None:
                lost = self._lost
                for name, values in neighbours.items():
                    if values is None and name not in lost:
                        self.inputs_missing.setdefault(name, []).append(k)
        self._taken_due = self._due(k)
        self.k = k
        if k + 1 >= self._first:
            self._prev = None  # the anchor before is done with
        return Tick(k, k * self.dt, skipped, neighbours, self.taken_due)

    def gather(
        self, k_prev: int, missing: frozenset[str], stale_ok: bool, *, wait: bool = True
    ) -> dict[str, np.ndarray | None] | None:
        """Neighbours' ``y_{k_prev}``, or ``None`` while one that is not missing is not in yet.

        Args:
            k_prev: the tick whose outputs are used.
            missing: neighbours that count as no data.
            stale_ok: a neighbour whose ``y_{k_prev}`` is not in gives its newest older output.
            wait: ``False``: a neighbour whose output is not in counts as no data (``None``)
                instead of making the whole result ``None``.
        """
        result: dict[str, np.ndarray | None] = {}
        for name in self.neighbours:
            history = self.history[name]
            values = history.get(k_prev)
            if values is not None:
                result[name] = values
            elif name in missing:
                result[name] = None
            elif stale_ok:
                older = [k for k in history if k < k_prev]
                result[name] = history[max(older)] if older else None
            elif wait:
                return None
            else:
                result[name] = None
        return result

    def counters(self) -> Mapping[str, int]:
        """Non-zero rejection counters (``dropped`` reasons and ``stale``), for status messages."""
        counts = {reason: n for reason, n in self.dropped.items() if n}
        if self.stale:
            counts["stale"] = self.stale
        return counts
