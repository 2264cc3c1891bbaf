"""Which frames the mocap process publishes (agents/mocap/decimation.py): closed-form cases."""

from __future__ import annotations

import pytest
from hilswarm.agents.bus import ScheduleMessage
from hilswarm.agents.mocap.decimation import PoseDecimator, next_due

P = 0.01  # 100 Hz frames [s]


def published(decimator: PoseDecimator, times: list[float]) -> list[int]:
    """Indices of the frames (times [s]) whose poses are published."""
    return [i for i, t in enumerate(times) if decimator.wanted(t)]


def test_without_a_schedule_every_frame_is_published() -> None:
    decimator = PoseDecimator(P, keep_alive=5)
    assert published(decimator, [i * P for i in range(20)]) == list(range(20))
    assert (decimator.published, decimator.left_out) == (20, 0)
    assert not decimator.decimating


def test_the_frame_a_tick_is_locked_to_and_the_one_before_are_published() -> None:
    # Ticks every 10 frames, each due 3 ms after frame 10 j + 5 (a locked tick's lag).
    decimator = PoseDecimator(P, keep_alive=1000)
    decimator.schedule = ScheduleMessage(first=0, last=100, t0=5 * P + 0.003, dt=10 * P)
    assert decimator.decimating
    frames = [i * P for i in range(40)]
    assert published(decimator, frames) == [4, 5, 14, 15, 24, 25, 34, 35]
    assert (decimator.published, decimator.left_out) == (8, 32)


def test_a_keep_alive_at_least_every_so_many_frames() -> None:
    decimator = PoseDecimator(P, keep_alive=4)
    decimator.schedule = ScheduleMessage(first=0, last=100, t0=9 * P + 0.003, dt=20 * P)
    # ticks' frames 8, 9 and 28, 29; in between one frame in four
    assert published(decimator, [i * P for i in range(30)]) == [3, 7, 8, 9, 13, 17, 21, 25, 28, 29]


def test_no_tick_outside_first_and_last() -> None:
    decimator = PoseDecimator(P, keep_alive=1000)
    # ticks 2..3 only: due at 20.3 and 30.3 frame periods' times
    decimator.schedule = ScheduleMessage(first=2, last=3, t0=0.3 * P, dt=10 * P)
    assert published(decimator, [i * P for i in range(50)]) == [19, 20, 29, 30]


def test_a_run_driven_by_tick_messages_gets_every_frame_from_then_on() -> None:
    decimator = PoseDecimator(P, keep_alive=1000)
    decimator.schedule = ScheduleMessage(first=0, last=100, t0=5 * P, dt=10 * P)
    decimator.every_frame()
    assert decimator.ticked and not decimator.decimating
    decimator.schedule = ScheduleMessage(first=0, last=100, t0=5 * P, dt=10 * P)  # a late one
    assert published(decimator, [i * P for i in range(12)]) == list(range(12))


@pytest.mark.parametrize(("period", "keep_alive"), [(0.0, 1), (-P, 1), (P, 0)])
def test_bad_parameters_are_refused(period: float, keep_alive: int) -> None:
    with pytest.raises(ValueError, match="must be"):
        PoseDecimator(period, keep_alive=keep_alive)


def test_next_due() -> None:
    schedule = ScheduleMessage(first=3, last=5, t0=1.0, dt=0.5)
    assert next_due(schedule, 0.0) == 2.5  # tick 3, the first
    assert next_due(schedule, 2.5) == 2.5
    assert next_due(schedule, 2.6) == 3.0
    assert next_due(schedule, 3.4) == 3.5
    assert next_due(schedule, 3.6) is None  # after the last
