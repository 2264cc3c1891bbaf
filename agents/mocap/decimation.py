"""Which frames' poses the mocap process publishes: those a tick can use, and a keep-alive. Pure.

``[mocap] tick_frames_only`` (off by default: docs/mocap.md has the measured trade-off). An
agent uses its body's pose once per control tick, when its vehicle senses. Every pose
published wakes every subscribed agent process (~0.1 ms of CPU per pose and agent, docs/
mocap.md): at 240 Hz frames and 23 Hz control nine poses in ten are received only to be
replaced by the next. Given the instance manager's schedule of a self-clocked run (tick ``j``,
``first <= j <= last``, due at ``t0 + j * dt`` on this host's CLOCK_MONOTONIC), the mocap
process publishes a frame's poses only when

* a tick is due less than two frame periods after the frame's time: the frame a tick is
  locked to and the one before it (a sense whose frame is still on its way uses that one, or
  waits for its own, ``pose_wait_ms``); or
* it is the ``keep_alive``-th frame since the last one published (so an agent never goes
  ``hold_s`` without a message while it waits for its next tick or while the run is paused:
  tracking loss stays what it was, the count of occluded frames travels in each message).

Without a schedule (a run driven by tick messages: remote agents, an XBee gateway,
``realtime_clock = "manager"``; or before the first schedule) every frame is published, as
is every frame once the run turns out to be driven by tick messages
(:meth:`PoseDecimator.every_frame`).

Times are [s] on the clock of the frame clock (``mocap_clock``: the frame's time on this
host's CLOCK_MONOTONIC), the clock the manager locks its ticks to.
"""

from __future__ import annotations

import math

from hilswarm.agents.bus import ScheduleMessage


def next_due(schedule: ScheduleMessage, after_s: float) -> float | None:
    """When the first tick of ``schedule`` due at or after ``after_s`` [s] is due (``None``:
    none is)."""
    j = max(schedule.first, math.ceil((after_s - schedule.t0) / schedule.dt))
    return None if j > schedule.last else schedule.t0 + j * schedule.dt


class PoseDecimator:
    """Decide per frame whether its poses are published (module docstring).

    Args:
        frame_period_s: the mocap system's frame period [s] (1 / rate).
        keep_alive: publish at least every ``keep_alive``-th frame (>= 1; 1: every frame).
    """

    def __init__(self, frame_period_s: float, *, keep_alive: int) -> None:
        if not (math.isfinite(frame_period_s) and frame_period_s > 0):
            raise ValueError(f"frame_period_s must be > 0 [s], got {frame_period_s!r}")
        if keep_alive < 1:
            raise ValueError(f"keep_alive must be >= 1 [frames], got {keep_alive!r}")
        self.frame_period_s = float(frame_period_s)
        self.keep_alive = int(keep_alive)
        #: The manager's newest schedule (``None``: every frame is published).
        self.schedule: ScheduleMessage | None = None
        #: ``True`` once the run turned out to be driven by tick messages (every frame).
        self.ticked = False
        self._unpublished = 0  # frames since the last one published
        #: Frames published and left out so far.
        self.published = 0
        self.left_out = 0

    def every_frame(self) -> None:
        """From now on publish every frame (the run is driven by tick messages)."""
        self.ticked = True
        self.schedule = None

    @property
    def decimating(self) -> bool:
        """Are frames being left out (a schedule is known and no tick message came)?"""
        return self.schedule is not None and not self.ticked

    def wanted(self, frame_time_s: float) -> bool:
        """Publish the poses of the frame of time ``frame_time_s`` [s]? (Counts the answer.)"""
        if self._publish(frame_time_s):
            self._unpublished = 0
            self.published += 1
            return True
        self._unpublished += 1
        self.left_out += 1
        return False

    def _publish(self, frame_time_s: float) -> bool:
        schedule = self.schedule
        if schedule is None or self.ticked or self._unpublished + 1 >= self.keep_alive:
            return True
        due = next_due(schedule, frame_time_s)
        return due is not None and due < frame_time_s + 2 * self.frame_period_s
