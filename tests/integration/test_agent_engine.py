"""The agent's tick engine without a bus: neighbour history and realtime staleness."""

from __future__ import annotations

import pytest
from hilswarm.agents import bus
from hilswarm.agents.agent import NEIGHBOUR_HISTORY, STALE_TICK_PERIODS, Agent, AgentConfig

DT = 0.01


def agent() -> Agent:
    config = AgentConfig(
        experiment="engine",
        name="b",
        agent_names=("a", "b"),
        neighbours=("a",),
        vehicle="simulated",
        link=None,
        controller="consensus",
        dt=DT,
    )
    return Agent(config, ["tcp/127.0.0.1:9"])  # never connected: no session is opened


def test_outputs_of_a_neighbour_running_a_window_ahead_are_all_kept() -> None:
    engine = agent()
    engine.k = 10
    for k in range(0, 30):  # the neighbour is up to 19 ticks ahead
        engine.receive_neighbour("a", bus.encode_vector(k, k * DT, [float(k)]))
    kept = sorted(engine._neighbour_y["a"])
    assert kept == list(range(10 - NEIGHBOUR_HISTORY, 30))


def test_a_bad_neighbour_message_raises() -> None:
    with pytest.raises(bus.BusMessageError):
        agent().receive_neighbour("a", b"short")


def test_realtime_ticks_that_queued_up_are_stale_and_a_moved_schedule_is_not() -> None:
    engine = agent()
    engine.k = 0
    clock = 100.0
    for k in range(1, 50):  # on schedule: a constant delay of 1 ms
        assert not engine._is_stale(k * DT, clock + k * DT + 0.001)
    # A 50 ms stall: ticks 50..54 arrive together, 45 us apart; only the fresh end runs.
    arrival = clock + 54 * DT + 0.0012
    verdicts = [engine._is_stale(k * DT, arrival + 45e-6 * (k - 50)) for k in range(50, 55)]
    assert verdicts[0] is False  # the first of a burst may be old, but nothing came before it
    assert verdicts[1:3] == [True, True]  # more than STALE_TICK_PERIODS late, right behind
    assert verdicts[-1] is False  # the newest one is on time
    assert STALE_TICK_PERIODS * DT < 0.02
    # A pause of 3 s (resume re-anchors the schedule): late, but alone, so not stale.
    assert not engine._is_stale(55 * DT, clock + 55 * DT + 3.0)
    assert not engine._is_stale(56 * DT, clock + 56 * DT + 3.0)


def test_tick_messages_carry_the_mode() -> None:
    for realtime in (False, True):
        message = bus.TickMessage(7, 0.07, (1, 3), realtime=realtime)
        assert bus.decode_tick(bus.encode_tick(message)) == message
    with pytest.raises(bus.BusMessageError):
        bus.decode_tick(bus.encode_tick(bus.TickMessage(1, 0.01, (2,)))[:-1])
