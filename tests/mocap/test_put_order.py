"""The order of a frame's body puts (agents/mocap/put_order.py): the bodies whose agents sense
at that frame first, in closed form (no clock, no process)."""

from __future__ import annotations

import pytest
from hilswarm.agents.bus import ScheduleMessage
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.put_order import PutOrder

F = 1.0 / 240.0  # frame period [s]
DT = 1.0 / 23.0  # control period [s]
LAG = 0.25e-3  # the ticks' lag after their frame [s]


def spread_order(agents: int, spread: int) -> PutOrder:
    settings = MocapSettings(system="sim", rate_hz=240.0, tick_spread_frames=spread)
    return PutOrder([settings.tick_phase_s(i) for i in range(agents)], F)


def test_the_agents_that_sense_at_a_frame_go_first() -> None:
    """16 agents spread over 8 frames: at the frame before each phase's due time, that
    phase's two bodies (i and i + 8) first, then the others in their own order."""
    order = spread_order(16, 8)
    assert order.spread
    # The lock's anchor: tick j due LAG after a frame (frames at 7 ms + n F).
    t0 = 0.007 + LAG
    order.schedule = ScheduleMessage(first=0, last=1000, t0=t0, dt=DT)
    for j in (0, 1, 57):
        for phase in range(8):
            frame = t0 + j * DT + phase * F - LAG  # the frame that phase's senses use
            got = order.order(frame)
            assert got[:2] == (phase, phase + 8), (j, phase, got)
            assert sorted(got) == list(range(16))
            assert got[2:] == tuple(i for i in range(16) if i % 8 != phase)
        # The frames after the spread's last phase: no agent senses, the bodies' own order.
        for extra in (8, 9, 10):
            frame = t0 + j * DT + extra * F - LAG
            if frame + F < t0 + (j + 1) * DT:  # not yet the next tick's first frame
                assert order.order(frame) == tuple(range(16))


def test_a_frame_just_before_the_due_time_is_the_one_used() -> None:
    """The frame of time h is used by a sense due in [h, h + F): one frame earlier is not."""
    order = spread_order(4, 4)
    order.schedule = ScheduleMessage(first=0, last=100, t0=1.0, dt=DT)
    assert order.order(1.0 + 2 * F - 0.9 * F)[0] == 2  # due 0.9 F after this frame
    assert order.order(1.0 + 2 * F)[0] == 2  # due at the frame's own time
    assert order.order(1.0 + 2 * F - 1.1 * F)[0] == 1  # a frame earlier: phase 1's


@pytest.mark.parametrize("agents,spread", [(16, 1), (1, 8), (0, 4)])
def test_without_a_spread_or_a_schedule_the_bodies_own_order(agents: int, spread: int) -> None:
    order = spread_order(agents, spread)
    assert not order.spread
    order.schedule = ScheduleMessage(first=0, last=100, t0=1.0, dt=DT)
    assert order.order(1.0) == tuple(range(agents))
    spread_16 = spread_order(16, 8)
    assert spread_16.order(1.0) == tuple(range(16))  # no schedule yet (or tick messages)


def test_a_frame_period_that_is_not_positive_is_refused() -> None:
    with pytest.raises(ValueError, match="frame_period_s"):
        PutOrder([0.0], 0.0)
