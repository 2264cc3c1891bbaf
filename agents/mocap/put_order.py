"""In which order the mocap process puts a frame's body poses: the bodies whose agents' ticks
use this frame first. Pure.

With ``[mocap] tick_spread_frames = N`` (self-clocked, ticks locked to the frames) agent i
ticks (i mod N) frame periods after the swarm's due time (docs/mocap.md, "Ticks spread over
the frames"), so at each frame only the agents of one phase sense, a lag after the frame
reached the host. Every body's pose of the frame is put, one after another, and each put
goes through the router to its agent after the ones before it: at 16 bodies and 240 Hz the
last body's pose reached its agent ~0.5 ms later than the first's (p50, docs/mocap.md). So
the bodies whose agents sense at this frame go first, the others (whose senses use a later
frame) after them.

Given the manager's schedule (tick ``j`` due at ``t0 + j * dt`` on this host's
CLOCK_MONOTONIC, the lock's anchor) an agent of phase ``p`` [s] senses at ``t0 + j * dt + p``,
which uses the frame of time ``h`` when ``0 <= t0 + j * dt + p - h < frame period`` (the lag
and the frame's way to the host are under a frame). Without a schedule (a run driven by tick
messages, or before the first) or without a spread: the bodies' own order.

Bodies are the agents' own, in the graph's order (the order the phases are counted in).
Times are [s] on the frame clock's clock (``mocap_clock``: the frame's time on this host's
CLOCK_MONOTONIC).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from hilswarm.agents.bus import ScheduleMessage


class PutOrder:
    """The order of a frame's body puts (module docstring).

    Args:
        phases_s: each body's agent's phase after the swarm's due time [s] (0 <= phase < dt).
        frame_period_s: the mocap system's frame period [s] (1 / rate).
    """

    def __init__(self, phases_s: Sequence[float], frame_period_s: float) -> None:
        if not (math.isfinite(frame_period_s) and frame_period_s > 0):
            raise ValueError(f"frame_period_s must be > 0 [s], got {frame_period_s!r}")
        self.frame_period_s = float(frame_period_s)
        phases = [float(p) for p in phases_s]
        #: The bodies' own order (indices).
        self.natural: tuple[int, ...] = tuple(range(len(phases)))
        self._phases = sorted(set(phases))
        self._orders = {
            p: tuple(i for i in self.natural if phases[i] == p)
            + tuple(i for i in self.natural if phases[i] != p)
            for p in self._phases
        }
        #: The manager's newest schedule (``None``: the bodies' own order).
        self.schedule: ScheduleMessage | None = None

    @property
    def spread(self) -> bool:
        """Do the agents sense at more than one phase (else the order never changes)?"""
        return len(self._phases) > 1

    def order(self, frame_time_s: float) -> tuple[int, ...]:
        """Body indices in the order to put the poses of the frame of time ``frame_time_s``."""
        schedule = self.schedule
        if schedule is None or not self.spread:
            return self.natural
        t0, dt, period = schedule.t0, schedule.dt, self.frame_period_s
        for phase in self._phases:
            if (t0 + phase - frame_time_s) % dt < period:
                return self._orders[phase]
        return self.natural
