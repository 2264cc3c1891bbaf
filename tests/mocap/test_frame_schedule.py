"""The manager's frame schedule (orchestrator/frame_schedule.py): frame-clock messages in, due
times and the ``frame_lock`` record out, with times passed in (no clock, no process)."""

from __future__ import annotations

import logging

import pytest
from hilswarm.agents.mocap import frame_clock
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.orchestrator.frame_lock import ACQUIRE_FRAMES
from hilswarm.orchestrator.frame_schedule import FRAME_LOCK_REPORT_S, FrameSchedule

P = 0.01  # 100 Hz frames [s]
DT = 0.01  # 100 Hz ticks [s]


def test_no_lock_without_mocap_or_in_lockstep_or_with_tick_lock_off() -> None:
    for schedule in (
        FrameSchedule(DT, None, realtime=True),
        FrameSchedule(DT, MocapSettings(system="sim"), realtime=False),
        FrameSchedule(DT, MocapSettings(system="sim", tick_lock=False), realtime=True),
    ):
        assert not schedule.locking
        schedule.start(2.0)
        assert schedule.due(3, 2.5) == pytest.approx(2.03)  # the free grid
        assert schedule.report(3, 2.5) is None
        assert schedule.report(3, 2.5, final=True) is None


def test_frames_lock_the_due_times_and_the_record_says_when() -> None:
    schedule = FrameSchedule(DT, MocapSettings(system="sim", rate_hz=100.0), realtime=True)
    assert schedule.locking
    lag = schedule.ticks.lag_s
    schedule.start(1.0)
    # No frames yet: free, and the first record says so.
    assert schedule.due(0, 1.0) == pytest.approx(1.0)
    schedule.released()
    assert schedule.report(0, 1.0) == "free: no mocap frames; ticks locked 0, free 1"
    assert schedule.report(0, 1.001) is None  # unchanged and not due again
    # Frames at 1.0043 + n P, reaching the manager 0.5 ms later: locked after acquisition.
    for n in range(ACQUIRE_FRAMES):
        f = 1.0043 + n * P
        schedule.on_frame(frame_clock.encode(n, f), f + 0.0005)
    now = 1.0043 + (ACQUIRE_FRAMES - 1) * P + 0.0005
    k = 11
    due = schedule.due(k, now)
    frame = due - lag  # a frame's arrival on the manager clock, the lag before the tick
    assert (frame - (1.0048 + k * P)) % P == pytest.approx(0.0, abs=1e-9)
    assert 0.0 <= frame - (1.0 + k * DT) < P  # the first frame at or after its grid point
    schedule.released()
    text = schedule.report(k, now)
    assert text is not None and text.startswith("locked: ticks ")
    assert text.endswith("ticks locked 1, free 1")
    assert schedule.report(k, now + 1.0) is None  # holds, not due yet
    assert schedule.report(k, now + FRAME_LOCK_REPORT_S) is not None  # every 10 s
    final = schedule.report(k, now + FRAME_LOCK_REPORT_S + 0.1, final=True)
    assert final is not None and final.startswith("locked: ")  # the end: always


def test_a_malformed_frame_clock_is_counted_and_warned_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    schedule = FrameSchedule(DT, MocapSettings(system="sim"), realtime=True)
    with caplog.at_level(logging.WARNING):
        schedule.on_frame(b"short", 1.0)
        schedule.on_frame(b"\x00" * 3, 1.1)
    assert schedule.malformed == 2
    assert sum("mocap frame clock dropped" in r.getMessage() for r in caplog.records) == 1
    schedule.start(0.0)
    assert schedule.due(5, 1.2) == pytest.approx(0.05)  # nothing locked on them


def test_tick_0_waits_for_the_frames_that_set_the_lock() -> None:
    """Before tick 0 the manager waits (bounded) until enough frames came for a lock: a run
    whose agents armed quickly would otherwise send its first ticks free."""
    assert FrameSchedule(DT, None, realtime=True).wait_acquired(0.0)  # no lock: no wait
    schedule = FrameSchedule(DT, MocapSettings(system="sim", rate_hz=100.0), realtime=True)
    assert not schedule.wait_acquired(0.01)  # no frames: the bound ends the wait
    for n in range(ACQUIRE_FRAMES - 1):
        schedule.on_frame(frame_clock.encode(n, 1.0 + n * P), 1.0005 + n * P)
    assert not schedule.wait_acquired(0.0)
    n = ACQUIRE_FRAMES - 1
    schedule.on_frame(frame_clock.encode(n, 1.0 + n * P), 1.0005 + n * P)
    assert schedule.wait_acquired(0.0)


@pytest.mark.parametrize(("self_clocked", "said"), [(True, True), (False, False)])
def test_the_record_says_when_the_ticks_spread(self_clocked: bool, said: bool) -> None:
    """``tick_spread_frames`` in a self-clocked run: the ``frame_lock`` record says it (with
    tick messages it has no effect, and the record says nothing of it)."""
    mocap = MocapSettings(system="sim", rate_hz=100.0, tick_spread_frames=3)
    schedule = FrameSchedule(DT, mocap, realtime=True, self_clocked=self_clocked)
    schedule.start(1.0)
    for n in range(ACQUIRE_FRAMES):
        schedule.on_frame(frame_clock.encode(n, 1.0 + n * P), 1.0 + n * P + 0.0005)
    now = 1.0 + ACQUIRE_FRAMES * P
    schedule.due(ACQUIRE_FRAMES, now)
    schedule.released()
    text = schedule.report(ACQUIRE_FRAMES, now)
    assert text is not None and text.startswith("locked: ")
    assert ("the agents' ticks spread over 3 frames" in text) is said


def test_a_moved_schedule_goes_out_once_the_ticks_senses_are_over() -> None:
    """A schedule the lock moved is sent after the tick's senses (the spread's frames after
    its due time, one frame without a spread), not into them; at once when that would leave
    the moved tick under a tenth of a period to get it, and without a lock."""
    dt = 1.0 / 23.0  # 23 Hz control [s]
    f = 1.0 / 240.0  # 240 Hz frames [s]
    spread = FrameSchedule(
        dt,
        MocapSettings(system="sim", rate_hz=240.0, tick_spread_frames=8),
        realtime=True,
        self_clocked=True,
    )
    due = 5.0
    # The moved tick one period on, within a frame either way: 8 frames leave 10.2 +- 4.2 ms.
    for shift in (-0.99 * f, 0.0, 0.99 * f):
        assert spread.quiet_send_time(due, due + dt + shift) == pytest.approx(due + 8 * f)
    # Under a tenth of a period after the senses: at once.
    assert spread.quiet_send_time(due, due + 8 * f + 0.09 * dt) == due
    # No spread: one frame after the tick, when no agent senses until the next tick.
    plain = FrameSchedule(
        dt, MocapSettings(system="sim", rate_hz=240.0), realtime=True, self_clocked=True
    )
    assert plain.quiet_send_time(due, due + dt) == pytest.approx(due + f)
    # With tick messages the spread has no effect: one frame as well.
    ticked = FrameSchedule(
        dt, MocapSettings(system="sim", rate_hz=240.0, tick_spread_frames=8), realtime=True
    )
    assert ticked.quiet_send_time(due, due + dt) == pytest.approx(due + f)
    # No lock (no mocap, or lockstep): nothing moves, at once.
    assert FrameSchedule(dt, None, realtime=True).quiet_send_time(due, due + dt) == due
