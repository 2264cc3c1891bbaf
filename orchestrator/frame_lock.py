"""Realtime ticks in step with the motion-capture frames: the frame phase and the tick schedule.

Free-running ticks meet the camera frames at any phase, so a pose waits between 0 and one frame
period for the tick that uses it (docs/mocap.md). With ``[mocap]`` the instance manager instead
releases tick k a small lag after a frame came: the tick's sense then uses that frame's pose.

* :class:`FrameLock` estimates, from the mocap process's frame-clock messages (frame number,
  frame time on the host's CLOCK_MONOTONIC, :mod:`hilswarm.agents.mocap.frame_clock`) and their
  arrival on the manager's clock, when every frame reaches the manager: frame ``n`` at
  ``f0 + phase + offset + (n - n0) P``. ``phase`` is a running minimum of each frame time
  against the frame grid (frames are late, never early: the earliest ones mark the grid),
  ``offset`` a running minimum of arrival minus frame time (the quickest delivery to the
  manager; it absorbs a camera latency and any offset between the clocks). Both minima rise
  slowly (``leak`` seconds per second), so they follow a frame clock that drifts against the
  host's (a real system's crystal); a jump (a restarted server, frames a client did not number)
  makes the estimator start over after :data:`JUMP_FRAMES` frames. No clock is read here:
  every time is passed in.
* :class:`TickClock` gives the due time of each tick: the free grid ``t0 + k dt``, or, while
  the lock holds, the first frame at or after that grid point plus the lag. When frames stop
  (no frame-clock message for ``timeout_s``), the next due time is the free grid point at once;
  the schedule locks again when frames come back. For an integer ratio of frame rate to tick
  rate (100/100, 200/100) every tick meets the same frame phase: the grid is anchored half a
  frame before a frame, and kept there as the phase drifts, so the lock is exact and robust to
  estimation noise. For other ratios (240/100) the grid is anchored when the lock is taken and
  the ticks' instants then jitter within one frame period; experiment time stays ``k dt``.

Everything here is O(1) per frame and per tick, with no allocation; the manager guards it with
a lock shared between its bus callback and its ticking thread.
"""

from __future__ import annotations

import math

#: Frames after a (re)start before the estimate is used.
ACQUIRE_FRAMES = 10
#: Consecutive frames later than half a period after the estimate that restart the estimator.
JUMP_FRAMES = 10
#: How fast the running minima may rise [s per s of frame time]: follows a frame clock that
#: drifts against the host's by up to 1000 ppm.
DEFAULT_LEAK = 1e-3


def default_timeout_s(frame_period_s: float) -> float:
    """How long without a frame-clock message before the ticks fall back to the free clock
    [s]: five frame periods plus 10 ms (a frame's message delayed on a loaded machine is not
    a lost server)."""
    return 5.0 * frame_period_s + 0.01


class FrameLock:
    """The frame phase on the manager's clock (see the module docstring).

    Args:
        frame_period_s: the mocap system's nominal frame period [s].
        timeout_s: no frame for this long [s]: not locked (default :func:`default_timeout_s`).
        leak: how fast the running minima may rise [s/s].
    """

    def __init__(
        self,
        frame_period_s: float,
        *,
        timeout_s: float | None = None,
        leak: float = DEFAULT_LEAK,
    ) -> None:
        if not frame_period_s > 0:
            raise ValueError(f"frame period must be > 0 s, got {frame_period_s!r}")
        self.period = float(frame_period_s)
        self.timeout_s = default_timeout_s(self.period) if timeout_s is None else timeout_s
        self.leak = leak
        #: Frames used since the estimator (re)started.
        self.frames = 0
        #: Times the estimator started over (after a gap, or a jump of the frames' phase).
        self.restarts = 0
        self._n0 = 0  # reference frame number and its frame time [s]
        self._f0 = 0.0
        self._phase = 0.0  # running minimum of f_n - f0 - (n - n0) P [s]
        self._offset = 0.0  # running minimum of arrival - f_n [s]
        self._last_f = 0.0
        self._last_arrival = -math.inf
        self._high_phase = 0
        self._high_offset = 0
        self._stats_count = 0
        self._stats_sum = 0.0
        self._stats_max = 0.0

    def _restart(self, number: int, frame_time: float, arrival: float) -> None:
        self.restarts += 1
        self.frames = 1
        self._n0, self._f0, self._phase = number, frame_time, 0.0
        self._offset = arrival - frame_time
        self._high_phase = self._high_offset = 0
        self._last_f, self._last_arrival = frame_time, arrival

    def on_frame(self, number: int, frame_time: float, arrival: float) -> None:
        """Frame ``number``, at ``frame_time`` [s, the frame clock], arrived at ``arrival``
        [s, the manager's clock]."""
        if self.frames == 0 or arrival - self._last_arrival > self.timeout_s:
            self._restart(number, frame_time, arrival)
            return
        period, half = self.period, 0.5 * self.period
        rise = self.leak * max(0.0, frame_time - self._last_f)
        self._last_f, self._last_arrival = frame_time, arrival
        residual = frame_time - self._f0 - (number - self._n0) * period
        phase = self._phase + rise
        if residual <= phase:
            phase, self._high_phase = residual, 0
        elif residual > phase + half:
            self._high_phase += 1
            if self._high_phase >= JUMP_FRAMES:
                self._restart(number, frame_time, arrival)
                return
        else:
            self._high_phase = 0
        self._phase = phase
        error = residual - phase
        if error <= half:  # how far the frame came after the estimated grid
            self._stats_count += 1
            self._stats_sum += error
            self._stats_max = max(self._stats_max, error)
        delay = arrival - frame_time
        offset = self._offset + rise
        if delay <= offset:
            offset, self._high_offset = delay, 0
        elif delay > offset + half:
            self._high_offset += 1
            if self._high_offset >= JUMP_FRAMES:
                offset, self._high_offset = delay, 0
        else:
            self._high_offset = 0
        self._offset = offset
        self.frames += 1

    @property
    def acquired(self) -> bool:
        """Enough frames came since the estimator (re)started to estimate the phase."""
        return self.frames >= ACQUIRE_FRAMES

    def locked(self, now: float) -> bool:
        """The estimate holds at ``now`` [s, manager clock]: enough frames, the last recent."""
        return self.acquired and now - self._last_arrival <= self.timeout_s

    @property
    def offset_s(self) -> float:
        """The quickest delivery of a frame to the manager (arrival - frame time) [s]."""
        return self._offset

    def next_frame(self, t: float) -> float:
        """The first frame's arrival at or after ``t`` [s, manager clock] (as estimated)."""
        base = self._f0 + self._phase + self._offset
        return base + math.ceil((t - base) / self.period) * self.period

    def take_stats(self) -> tuple[int, float, float]:
        """``(frames, mean, max)`` of the frames' delay after the estimated grid [s] since the
        last call (the phase error of the lock); then starts counting again."""
        count, total, top = self._stats_count, self._stats_sum, self._stats_max
        self._stats_count, self._stats_sum, self._stats_max = 0, 0.0, 0.0
        return count, (total / count if count else math.nan), (top if count else math.nan)


class TickClock:
    """Due times of realtime ticks, free or locked to the frames (see the module docstring).

    Args:
        dt: tick period [s].
        lock: the frame phase (``None``: always free).
        lag_s: a locked tick is due this long after its frame reaches the manager [s].
    """

    def __init__(self, dt: float, lock: FrameLock | None = None, lag_s: float = 0.0) -> None:
        self.dt = dt
        self.lock = lock
        self.lag_s = lag_s
        period = lock.period if lock is not None else math.inf
        #: Ticks can lock: there is a frame clock and ticks are no faster than frames.
        self.enabled = lock is not None and dt >= period * (1.0 - 1e-9)
        ratio = dt / period if self.enabled else 0.0
        #: Frame rate / tick rate is an integer: every tick meets the frames at one phase.
        self.integer_ratio = self.enabled and abs(ratio - round(ratio)) < 1e-3
        #: Origin of the free grid [s, manager clock]: tick k at ``t0 + k dt``.
        self.t0 = 0.0
        #: The last due time given was locked to a frame.
        self.locked = False
        #: Ticks sent at a locked / free due time (:meth:`released`).
        self.ticks_locked = 0
        self.ticks_free = 0
        self._k = -1
        self._due = 0.0
        self._anchored = False

    def start(self, t0: float) -> None:
        """Tick 0's grid point is ``t0`` [s]."""
        self.t0 = t0
        self._k, self._anchored = -1, False

    def reanchor(self, now: float, k: int) -> None:
        """Resume after a pause: tick ``k + 1`` is due one period after ``now`` [s] (free), or
        at the first frame at or after that plus the lag."""
        self.start(now - k * self.dt)

    def due(self, k: int, now: float) -> float:
        """The due time of tick ``k`` [s, manager clock], as known at ``now``."""
        grid = self.t0 + k * self.dt
        lock = self.lock
        if lock is None or not self.enabled or not lock.locked(now):
            self._k, self.locked, self._anchored = k, False, False
            return grid
        if k == self._k and self.locked:
            return self._due  # once per tick: estimation noise cannot move it to another frame
        period = lock.period
        frame = lock.next_frame(grid)
        if not self._anchored or (
            self.integer_ratio and not 0.25 * period <= frame - grid <= 0.75 * period
        ):
            # the grid half a frame before this frame: the tick keeps its frame, and (integer
            # ratios) every later tick meets its frame half a period after its grid point
            self.t0 += frame - 0.5 * period - grid
            self._anchored = True
        self._k, self.locked, self._due = k, True, frame + self.lag_s
        return self._due

    def released(self) -> None:
        """The tick of the last due time was sent: count it as locked or free."""
        if self.locked:
            self.ticks_locked += 1
        else:
            self.ticks_free += 1
