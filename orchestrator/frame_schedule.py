"""The instance manager's realtime due times, free or in step with the mocap frames.

:class:`FrameSchedule` is what the manager holds of :mod:`hilswarm.orchestrator.frame_lock`:
the frame phase (:class:`~hilswarm.orchestrator.frame_lock.FrameLock`), fed by the mocap
process's frame-clock messages on a Zenoh thread, and the ticks' due times
(:class:`~hilswarm.orchestrator.frame_lock.TickClock`), asked by the ticking thread, behind
one small lock of their own; and the ``frame_lock`` record on ``/orchestrator/status`` that
says how the lock holds (docs/mocap.md, "Ticks in step with the frames"). No clock is read
here: every time is passed in [s, the manager's clock].
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

from hilswarm.agents import bus
from hilswarm.agents.mocap import frame_clock
from hilswarm.orchestrator.frame_lock import FrameLock, TickClock

logger = logging.getLogger(__name__)

#: Period of the ``frame_lock`` record while the lock holds [s].
FRAME_LOCK_REPORT_S = 10.0
#: How long a frame-locked run waits before tick 0 for the frames that set the lock [s].
FRAME_ACQUIRE_WAIT_S = 2.0
#: A schedule moved by the lock goes out after the agents' senses only if that is at least
#: this fraction of a tick period before the tick it moves (4.3 ms at 23 Hz, above a pose's
#: p99 delivery to 16 agents on a loaded 2-core machine, 3-4 ms). A schedule that comes later
#: still only shifts that one tick by under a frame.
SCHEDULE_LEAD_FRACTION = 0.1


class FrameSchedule:
    """Due times of realtime ticks, locked to the frames when the experiment asks for it.

    Args:
        dt: tick period [s].
        mocap: the experiment's ``[mocap]`` section (``None``: none); its ``tick_lock``,
            ``rate_hz`` and ``tick_lag_s`` are used.
        realtime: the run is realtime (lockstep ticks never lock).
        self_clocked: the agents keep the schedule themselves, so the ticks' spread over the
            frames (``tick_spread_frames``) applies; the record says so.
    """

    def __init__(
        self, dt: float, mocap: Any | None, *, realtime: bool, self_clocked: bool = False
    ) -> None:
        self._guard = threading.Lock()  # the frame-clock callback against the ticking thread
        self.dt = float(dt)
        self.lock: FrameLock | None = None
        #: Frames the agents' ticks spread over (1: none, or not in effect in this run).
        self.spread = 1
        if realtime and mocap is not None and mocap.tick_lock:
            self.lock = FrameLock(1.0 / mocap.rate_hz)
            if self_clocked:
                self.spread = mocap.tick_spread_frames
        lag_s = mocap.tick_lag_s if self.lock is not None else 0.0
        self.ticks = TickClock(dt, self.lock, lag_s)
        #: Frame-clock messages dropped as malformed (only the mocap principal may put them).
        self.malformed = 0
        self._reported: bool | None = None  # locked at the last record
        self._report_due = 0.0
        self._acquired = threading.Event()  # enough frames came for a lock

    @property
    def locking(self) -> bool:
        """Ticks follow the frames while frames come (``[mocap] tick_lock`` in a realtime run)."""
        return self.lock is not None

    def on_frame(self, payload: bytes, arrival: float) -> None:
        """A frame-clock message (a Zenoh thread, 100-240 Hz): one O(1) update of the phase.

        Args:
            payload: the message (:mod:`hilswarm.agents.mocap.frame_clock`); a malformed one
                is counted and dropped.
            arrival: when it came [s, manager clock].
        """
        try:
            number, frame_time = frame_clock.decode(payload)
        except bus.BusMessageError as exc:
            self.malformed += 1
            if self.malformed == 1:
                logger.warning("mocap frame clock dropped: %s", exc)
            return
        lock = self.lock
        if lock is not None:
            with self._guard:
                lock.on_frame(number, frame_time, arrival)
                acquired = lock.acquired
            if acquired and not self._acquired.is_set():
                self._acquired.set()

    def wait_acquired(self, timeout_s: float) -> bool:
        """Before tick 0: wait until enough frames came for a lock, at most ``timeout_s`` [s].

        The agents wait for their first pose before they arm, but the manager's own frame
        clock needs a few frames to find the phase (:attr:`FrameLock.acquired`): a run that
        starts sooner would send its first ticks free. ``True`` at once without a frame
        lock; ``False`` when the frames did not come (the ticks then start free, and the
        ``frame_lock`` record says so).
        """
        return self.lock is None or self._acquired.wait(timeout_s)

    def start(self, t0: float) -> None:
        """Tick 0's grid point is ``t0`` [s, manager clock]."""
        with self._guard:
            self.ticks.start(t0)

    def due(self, k: int, now: float) -> float:
        """The due time of tick ``k`` [s, manager clock], locked or free, as known at ``now``."""
        with self._guard:
            return self.ticks.due(k, now)

    def reanchor(self, now: float, k: int) -> None:
        """Resume: tick ``k + 1`` is due one period after ``now`` [s] (or at the frame then)."""
        with self._guard:
            self.ticks.reanchor(now, k)

    def quiet_send_time(self, due: float, next_due: float) -> float:
        """When a schedule that the lock moved at the tick due at ``due`` should go out [s,
        manager clock]; ``next_due``: when the tick it moves is due.

        Every agent takes a schedule message in (a wake-up of its bus thread and its worker,
        16 at once with 16 agents). Sent at ``due`` it meets the agents that sense then, and
        the poses they wait for. So it goes out once the tick's senses are over: the spread's
        frames after ``due`` (one frame without a spread), where no agent senses until the
        next tick. At ``due`` (at once) when that would leave the moved tick less than
        :data:`SCHEDULE_LEAD_FRACTION` of a period to get it, and without a frame lock.
        """
        lock = self.lock
        if lock is None:
            return due
        quiet = due + self.spread * lock.period
        return quiet if next_due - quiet >= SCHEDULE_LEAD_FRACTION * self.dt else due

    def released(self) -> None:
        """The tick of the last due time went out: counted as locked or free."""
        with self._guard:
            self.ticks.released()

    def report(self, k: int, now: float, *, final: bool = False) -> str | None:
        """The ``frame_lock`` record's text when one is due at tick ``k``: when the lock was
        taken or lost, every :data:`FRAME_LOCK_REPORT_S` while it holds, and at the end
        (``final``); ``None`` otherwise, and always without a frame lock."""
        lock, ticks = self.lock, self.ticks
        if lock is None:
            return None
        locked = ticks.locked
        if not final and locked is self._reported and now < self._report_due:
            return None
        with self._guard:
            frames, mean, top = lock.take_stats()
            offset = lock.offset_s
        if locked:
            detail = (
                f"locked: ticks {ticks.lag_s * 1e3:.3g} ms after frames "
                f"({offset * 1e3:.3g} ms after their frame time); frames after the estimated "
                f"grid: mean {mean * 1e3:.3g} / max {top * 1e3:.3g} ms ({frames} frames)"
            )
            if self.spread > 1:
                detail += f"; the agents' ticks spread over {self.spread} frames"
        elif not ticks.enabled:
            detail = "free: ticks faster than the mocap frames"
        else:
            detail = "free: no mocap frames"
        detail += f"; ticks locked {ticks.ticks_locked}, free {ticks.ticks_free}"
        if locked != self._reported:
            logger.info("tick %d: %s", k, detail)
        self._reported = locked
        self._report_due = math.inf if final else now + FRAME_LOCK_REPORT_S
        return detail
