"""The pure tick engine: release horizon, window, history, staleness, gather, rejections."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.tick_engine import (
    NEIGHBOUR_HISTORY,
    PREROLL_PERIOD_MAX_S,
    PREROLL_TICKS,
    REALTIME_SLACK_TICKS,
    SCHEDULE_AHEAD_PERIODS,
    SCHEDULE_START_LAG_PERIODS,
    STALE_TICK_PERIODS,
    TickEngine,
    is_warmup,
    preroll_times,
    start_lead,
)
from hypothesis import given, settings
from hypothesis import strategies as st

DT = 0.01
NAMES = ("a", "b", "c")


def engine(
    window: int = 8, neighbours: tuple[str, ...] = ("a", "c"), phase_s: float = 0.0
) -> TickEngine:
    e = TickEngine(neighbours, NAMES, DT, window, phase_s=phase_s)
    e.running = True
    return e


def y(k: int, value: float = 0.0) -> np.ndarray:
    return np.array([value + k])


def feed(e: TickEngine, k: int, *names: str) -> None:
    for name in names or e.neighbours:
        e.on_neighbour(name, k, y(k))


def test_lockstep_steps_through_every_released_tick_once_inputs_are_in() -> None:
    e = engine()
    assert e.take(gather=True) is None  # nothing released
    assert e.on_tick(3, 3 * DT, (), False, arrived=0.0)
    tick = e.take(gather=True)
    assert tick is not None and (tick.k, tick.skipped, tick.neighbours) == (0, 0, None)
    assert e.take(gather=True) is None  # tick 1 needs every neighbour's y_0
    feed(e, 0, "a")
    assert e.take(gather=True) is None
    feed(e, 0, "c")
    tick = e.take(gather=True)
    assert tick is not None and tick.k == 1 and tick.t == pytest.approx(DT)
    assert {n: v[0] for n, v in tick.neighbours.items()} == {"a": 0.0, "c": 0.0}


def test_only_the_last_input_a_released_tick_waits_for_wakes_the_worker() -> None:
    """One wake per tick, not one per neighbour: a worker woken by the first of two outputs
    would find the tick still waiting and sleep again (a context switch per neighbour)."""
    e = engine()
    e.on_tick(3, 3 * DT, (), False, arrived=0.0)
    e.take(gather=True)  # tick 0
    assert not e.on_neighbour("c", 0, y(0))  # a's y_0 is still on its way
    assert not e.on_neighbour("c", 1, y(1))  # for tick 2, which waits for tick 1 first
    assert e.on_neighbour("a", 0, y(0))  # the last one tick 1 waits for
    assert e.take(gather=True).k == 1
    assert e.on_neighbour("a", 1, y(1))  # c's y_1 came early: this one completes tick 2
    assert e.take(gather=True).k == 2
    e.on_tick(4, 4 * DT, (0,), False, arrived=0.0)  # a lost: tick 3 waits for c alone
    assert e.on_neighbour("c", 2, y(2))
    realtime = engine()
    realtime.on_tick(0, 0.0, (), True, arrived=0.0)
    realtime.take(gather=True)
    realtime.on_tick(1, DT, (), True, arrived=DT)
    assert not realtime.on_neighbour("a", 0, y(0))
    assert realtime.on_neighbour("c", 0, y(0))


@settings(max_examples=300, deadline=None)
@given(
    realtime=st.booleans(),
    events=st.lists(
        st.tuples(st.sampled_from(("tick", "a", "c", "lose")), st.integers(0, 12)),
        max_size=80,
    ),
)
def test_property_a_runnable_tick_always_comes_with_a_wake(
    realtime: bool, events: list[tuple[str, int]]
) -> None:
    """Whatever order ticks and outputs arrive in: after an input that did not wake the
    worker, the worker (asleep) has nothing to run; after one that did, it runs every tick
    ready. So waking once per tick never leaves a tick waiting for a wake that never comes."""
    e = engine()
    released = -1
    for kind, value in events:
        if kind == "tick":
            released += 2 if value % 5 == 4 else 1  # now and then a tick is skipped
            woke = e.on_tick(released, released * DT, (), realtime, arrived=released * DT)
        elif kind == "lose":  # the next tick reports agent a lost
            released += 1
            woke = e.on_tick(released, released * DT, (0,), realtime, arrived=released * DT)
        else:
            k = (e.k, e.horizon - 1, e.k + 1, e.k - 1)[value % 4]  # mostly the ones awaited
            woke = e.on_neighbour(kind, max(0, k), y(value))
        if woke:
            while e.take(gather=True) is not None:
                pass
        else:
            assert e.take(gather=True) is None, (kind, value, e.k, e.horizon)


def test_lockstep_never_runs_more_than_its_window_ahead_whatever_arrives() -> None:
    e = engine(window=4)
    for k in (4, 5, 1_000_000, 2**62):  # forged: further than the window past tick -1
        assert not e.on_tick(k, k * DT, (), False, arrived=0.0)
    assert e.dropped["tick_ahead"] == 4
    assert e.on_tick(3, 3 * DT, (), False, arrived=0.0)
    taken = []
    while (tick := e.take(gather=False)) is not None:
        taken.append(tick.k)
    assert taken == [0, 1, 2, 3]
    assert not e.on_tick(8, 8 * DT, (), False, arrived=0.0)  # 3 + 4 = 7 at most
    assert e.on_tick(7, 7 * DT, (), False, arrived=0.0)


def test_ticks_from_the_past_of_another_mode_or_with_a_wrong_time_are_rejected() -> None:
    e = engine()
    assert e.on_tick(5, 5 * DT, (), False, arrived=0.0)
    assert e.on_tick(5, 5 * DT, (1,), False, arrived=0.0)  # a loss announced again: accepted
    assert not e.on_tick(4, 4 * DT, (), False, arrived=0.0)
    assert not e.on_tick(6, 6 * DT, (), True, arrived=0.0)
    assert not e.on_tick(6, 1.0, (), False, arrived=0.0)
    assert not e.on_tick(-1, -DT, (), False, arrived=0.0)
    assert not e.on_tick(6, 6 * DT, (3,), False, arrived=0.0)  # no agent 3
    assert e.counters() == {
        "tick_past": 1,
        "tick_mode": 1,
        "tick_time": 2,
        "tick_missing": 1,
    }
    assert e.horizon == 5


def test_a_lost_agent_counts_as_no_data_from_then_on() -> None:
    e = engine()
    e.on_tick(3, 3 * DT, (0,), False, arrived=0.0)  # agent 0 = a is lost
    assert e.take(gather=True).k == 0
    feed(e, 0, "c")
    tick = e.take(gather=True)
    assert tick.neighbours["a"] is None and tick.neighbours["c"][0] == 0.0


def test_outputs_of_a_neighbour_running_a_window_ahead_are_all_kept() -> None:
    e = engine(window=32)
    e.on_tick(10, 10 * DT, (), False, arrived=0.0)
    for _ in range(11):
        e.take(gather=False)
    assert e.k == 10
    for k in range(0, 30):  # the neighbour is up to 19 ticks ahead
        e.on_neighbour("a", k, y(k))
    assert sorted(e.history["a"]) == list(range(10 - NEIGHBOUR_HISTORY, 30))


def test_neighbour_outputs_beyond_the_window_duplicates_and_resized_are_rejected() -> None:
    e = engine(window=4)
    assert not e.on_neighbour("a", 1_000_000, y(0))
    assert not e.on_neighbour("a", 5, y(0))  # tick 5 cannot be released yet (-1 + 4 + 1 = 4)
    e.on_neighbour("a", 4, y(4))
    assert not e.on_neighbour("a", 4, y(99))  # a second y_4: the first one stays
    assert e.history["a"][4][0] == 4
    assert not e.on_neighbour("a", 3, np.zeros(3))  # a has one output
    assert e.counters() == {"y_ahead": 2, "y_duplicate": 1, "y_size": 1}


def test_a_flood_of_forged_outputs_never_evicts_the_ones_a_tick_needs() -> None:
    e = engine(window=4)
    e.on_tick(0, 0.0, (), False, arrived=0.0)
    e.take(gather=True)
    feed(e, 0)
    for k in range(10**4):
        e.on_neighbour("a", 10**6 + k, y(0))
    assert e.on_tick(1, DT, (), False, arrived=0.0)
    assert e.take(gather=True).neighbours["a"][0] == 0.0


def test_realtime_runs_the_newest_tick_and_counts_the_skipped_ones() -> None:
    e = engine()
    e.on_tick(0, 0.0, (), True, arrived=100.0)
    assert e.take(gather=True).k == 0
    for k in range(1, 4):  # the agent was busy: ticks 1..3 came in on time
        assert e.on_tick(k, k * DT, (), True, arrived=100.0 + k * DT)
    feed(e, 1, "a")  # y_1 of a; c's y_2 is older than y_2 needed... realtime takes what it has
    feed(e, 2, "c")
    tick = e.take(gather=True)
    assert (tick.k, tick.skipped) == (3, 2)
    assert tick.neighbours["a"][0] == 1.0  # the newest older output
    assert tick.neighbours["c"][0] == 2.0


def test_realtime_ticks_that_queued_up_are_stale_and_a_moved_schedule_is_not() -> None:
    e = engine()
    clock = 100.0
    e.on_tick(0, 0.0, (), True, arrived=clock)
    e.take(gather=False)
    for k in range(1, 50):  # on schedule: a constant delay of 1 ms
        assert e.on_tick(k, k * DT, (), True, arrived=clock + k * DT + 0.001)
    e.take(gather=False)
    # A 50 ms stall: ticks 50..54 arrive together, 45 us apart; only the newest runs.
    arrival = clock + 54 * DT + 0.0012
    for k in range(50, 55):
        assert e.on_tick(k, k * DT, (), True, arrived=arrival + 45e-6 * (k - 50))
    assert e.stale == 2  # 51, 52: more than STALE_TICK_PERIODS late, right behind another
    assert STALE_TICK_PERIODS * DT < 0.02
    tick = e.take(gather=False)
    assert (tick.k, tick.skipped) == (54, 4)
    assert e.take(gather=False) is None
    # A pause of 3 s (resume re-anchors the schedule): late, but alone, so accepted.
    assert e.on_tick(55, 55 * DT, (), True, arrived=clock + 55 * DT + 3.0)
    assert e.on_tick(56, 56 * DT, (), True, arrived=clock + 56 * DT + 3.0)


def test_realtime_forged_future_ticks_are_rejected_and_do_not_freeze_the_schedule() -> None:
    e = engine()
    assert not e.on_tick(10**6, 10**6 * DT, (), True, arrived=0.0)  # a first tick is small
    e.on_tick(0, 0.0, (), True, arrived=0.0)
    for k in range(1, 20):
        assert e.on_tick(k, k * DT, (), True, arrived=k * DT)
        assert not e.on_tick(k + 1000, (k + 1000) * DT, (), True, arrived=k * DT + 1e-4)
        assert not e.on_tick(k - 1, (k - 1) * DT, (), True, arrived=k * DT + 2e-4)  # replay
    assert e.horizon == 19
    assert e.dropped["tick_ahead"] == 20 and e.dropped["tick_past"] == 19


@settings(max_examples=200, deadline=None)
@given(
    window=st.integers(1, 64),
    messages=st.lists(
        st.tuples(st.integers(-5, 10**9), st.booleans(), st.integers(0, 3)), max_size=60
    ),
)
def test_property_lockstep_never_takes_more_than_window_past_its_last_tick(
    window: int, messages: list[tuple[int, bool, int]]
) -> None:
    """Whatever tick messages arrive, in any order, each taken tick is the next one, and the
    horizon never exceeds the last taken tick plus the window."""
    e = engine(window=window, neighbours=())
    last = -1
    for k, take, n_take in messages:
        e.on_tick(k, k * DT, (), False, arrived=0.0)
        assert e.horizon <= last + window
        if take:
            for _ in range(n_take):
                tick = e.take(gather=True)
                if tick is None:
                    break
                assert tick.k == last + 1
                last = tick.k


@settings(max_examples=200, deadline=None)
@given(
    jitter=st.lists(st.floats(0.0, 0.004), min_size=5, max_size=80),
    forged=st.lists(st.integers(3, 10**6), max_size=10),
)
def test_property_realtime_accepts_every_genuine_tick_on_time_and_no_forged_one(
    jitter: list[float], forged: list[int]
) -> None:
    """Genuine ticks on schedule (with bus jitter below a period) are all accepted; ticks
    claiming more than the slack ahead of the elapsed periods never are."""
    e = engine(neighbours=())
    for k, delay in enumerate(jitter):
        arrived = 50.0 + k * DT + delay
        for ahead in forged if k else ():  # forgeries right before each genuine tick
            assert ahead > REALTIME_SLACK_TICKS
            assert not e.on_tick(k + ahead, (k + ahead) * DT, (), True, arrived=arrived - 1e-5)
        assert e.on_tick(k, k * DT, (), True, arrived=arrived), k
        e.take(gather=False)
    assert e.k == len(jitter) - 1


def test_tick_messages_carry_the_mode() -> None:
    for realtime in (False, True):
        message = bus.TickMessage(7, 0.07, (1, 3), realtime=realtime)
        assert bus.decode_tick(bus.encode_tick(message)) == message
    with pytest.raises(bus.BusMessageError):
        bus.decode_tick(bus.encode_tick(bus.TickMessage(1, 0.01, (2,)))[:-1])


def test_engine_arguments_are_checked() -> None:
    with pytest.raises(ValueError, match="dt"):
        TickEngine((), NAMES, 0.0, 1)
    with pytest.raises(ValueError, match="window"):
        TickEngine((), NAMES, DT, 0)


# -- self-clocked realtime: the manager's schedule -------------------------------------------

T0 = 1000.0  # when tick 0 is due [s, the shared monotonic clock]


def clocked(last: int = 10**6, first: int = 0, t0: float = T0, **kwargs: object) -> TickEngine:
    e = engine(**kwargs)
    assert e.on_schedule(first, last, t0, DT, arrived=t0 + first * DT - 0.05)
    return e


def test_self_clocked_ticks_are_due_at_t0_plus_k_dt_and_run_with_the_inputs_that_are_in() -> None:
    e = clocked()
    assert e.next_due() == T0
    assert e.take(gather=True, now=T0 - 1e-6) is None  # not due yet
    tick = e.take(gather=True, now=T0)
    assert (tick.k, tick.t, tick.skipped, tick.neighbours) == (0, 0.0, 0, None)
    assert e.next_due() == pytest.approx(T0 + DT)
    feed(e, 0, "a")  # c's y_0 is not in when tick 1 is due: no wait, no data for c
    assert not e.on_neighbour("c", 5, y(5), arrived=T0 + 0.5 * DT)  # too far ahead
    tick = e.take(gather=True, now=T0 + DT + 1e-4)
    assert tick.k == 1 and tick.neighbours["a"][0] == 0.0 and tick.neighbours["c"] is None
    assert e.inputs_missing == {"c": [1]}
    assert e.take_inputs_missing() == {"c": [1]} and e.inputs_missing == {}
    assert e.counters() == {"y_ahead": 1}


def test_self_clocked_agent_behind_runs_the_newest_due_tick_and_counts_the_skipped() -> None:
    e = clocked()
    e.take(gather=False, now=T0)
    feed(e, 0)
    feed(e, 2, "a")  # a ran ahead meanwhile
    tick = e.take(gather=True, now=T0 + 4.5 * DT)  # stalled: ticks 1..3 were due
    assert (tick.k, tick.skipped) == (4, 3)
    assert tick.neighbours["a"][0] == 2.0 and tick.neighbours["c"][0] == 0.0  # newest older
    assert e.take(gather=True, now=T0 + 4.5 * DT) is None


def test_self_clocked_lost_neighbours_are_no_data_and_not_noted_missing() -> None:
    e = clocked()
    assert e.on_schedule(0, 10**6, T0, DT, missing=(0,), arrived=T0)  # a is lost: same anchor
    e.take(gather=False, now=T0)
    feed(e, 0, "c")
    tick = e.take(gather=True, now=T0 + DT)
    assert tick.neighbours["a"] is None and e.inputs_missing == {}


def test_a_schedule_ends_at_its_last_tick_and_a_new_anchor_resumes_it() -> None:
    e = clocked()
    for k in range(3):
        assert e.take(gather=False, now=T0 + k * DT).k == k
    assert e.on_schedule(0, 3, T0, DT, arrived=T0 + 2.5 * DT)  # pause: ends after tick 3
    assert e.take(gather=False, now=T0 + 3 * DT).k == 3
    assert e.next_due() is None
    assert e.take(gather=False, now=T0 + 100.0) is None  # paused: nothing is due
    resume = T0 + 100.0  # re-anchored: tick 4 is due one period after the resume
    t1 = resume - 3 * DT
    assert e.on_schedule(4, 10**6, t1, DT, arrived=resume + 1e-4)
    assert e.next_due() == pytest.approx(resume + DT)
    tick = e.take(gather=False, now=resume + DT)
    assert (tick.k, tick.skipped) == (4, 0)


def test_a_moved_anchor_arriving_early_keeps_the_ticks_before_it_on_time() -> None:
    """The manager moves the schedule (a frame lock) from tick 3 on while the agent has not
    run tick 2 yet: tick 2 still runs at its time, tick 3 at the moved one; none skipped."""
    e = clocked()
    for k in range(2):
        e.take(gather=False, now=T0 + k * DT)
    moved = T0 + 0.3 * DT
    assert e.on_schedule(3, 10**6, moved, DT, arrived=T0 + 1.9 * DT)
    assert e.next_due() == pytest.approx(T0 + 2 * DT)
    tick = e.take(gather=False, now=T0 + 2 * DT + 1e-5)
    assert (tick.k, tick.skipped) == (2, 0)
    assert e.next_due() == pytest.approx(moved + 3 * DT)
    assert e.take(gather=False, now=moved + 3 * DT - 1e-6) is None
    tick = e.take(gather=False, now=moved + 3 * DT)
    assert (tick.k, tick.skipped) == (3, 0)
    assert e.next_due() == pytest.approx(moved + 4 * DT)


def test_a_phase_makes_each_tick_due_that_long_after_the_swarms() -> None:
    """``phase_s`` (``[mocap] tick_spread_frames``): tick k is due at ``t0 + k dt + phase``,
    also across a moved anchor; the tick's ``due`` says when; tick messages have none."""
    phase = 0.4 * DT
    e = clocked(phase_s=phase)
    assert e.next_due() == pytest.approx(T0 + phase)
    assert e.take(gather=False, now=T0 + phase - 1e-6) is None  # the swarm's due time: not yet
    tick = e.take(gather=False, now=T0 + phase)
    assert (tick.k, tick.skipped) == (0, 0) and tick.due == pytest.approx(T0 + phase)
    assert e.take(gather=False, now=T0 + DT + phase - 1e-6) is None  # not tick 1 yet
    tick = e.take(gather=False, now=T0 + 1.9 * DT)  # between tick 1 (+phase) and tick 2's
    assert (tick.k, tick.skipped) == (1, 0) and tick.due == pytest.approx(T0 + DT + phase)
    moved = T0 + 0.3 * DT  # the frame lock moves the anchor from tick 3 on
    assert e.on_schedule(3, 10**6, moved, DT, arrived=T0 + 1.95 * DT)
    assert e.next_due() == pytest.approx(T0 + 2 * DT + phase)  # tick 2 on the old anchor
    assert e.take(gather=False, now=T0 + 2 * DT + phase).k == 2
    assert e.next_due() == pytest.approx(moved + 3 * DT + phase)
    tick = e.take(gather=False, now=moved + 3 * DT + phase)
    assert (tick.k, tick.skipped) == (3, 0) and e.taken_due == tick.due
    ticked = engine()
    ticked.on_tick(0, 0.0, (), realtime=True, arrived=T0)
    assert math.isnan(ticked.take(gather=False).due)  # a tick message's: no due time
    for bad in (-1e-3, DT, math.nan):
        with pytest.raises(ValueError, match="phase_s"):
            TickEngine((), NAMES, DT, 8, phase_s=bad)


def test_forged_or_odd_schedules_are_rejected_and_counted() -> None:
    e = engine()
    arrived = T0 - 0.05
    assert not e.on_schedule(0, 100, T0, 2 * DT, arrived=arrived)  # another period
    assert not e.on_schedule(0, 100, math.nan, DT, arrived=arrived)
    assert not e.on_schedule(5, 4, T0, DT, arrived=arrived)  # ends before it begins
    assert not e.on_schedule(0, 100, T0, DT, missing=(3,), arrived=arrived)  # no agent 3
    far = T0 + SCHEDULE_AHEAD_PERIODS * DT + 0.06
    assert not e.on_schedule(0, 100, far, DT, arrived=arrived)  # would freeze the agent
    assert not e.on_schedule(10**6, 10**7, T0, DT, arrived=arrived)  # a run begins at 0
    old = T0 - (SCHEDULE_START_LAG_PERIODS + 2) * DT
    assert not e.on_schedule(0, 10**7, old, DT, arrived=T0)  # would race it ahead
    assert e.counters() == {"schedule_dt": 1, "schedule_time": 5, "tick_missing": 1}
    assert e.on_schedule(0, 100, T0, DT, arrived=arrived)  # the genuine one
    for k in range(5):
        e.take(gather=False, now=T0 + k * DT)
    # Once running: a new anchor may not put it further ahead than the time elapsed allows.
    assert not e.on_schedule(0, 100, T0 - 1.0, DT, arrived=T0 + 4.2 * DT)
    assert not e.on_schedule(0, 100, T0 + 1.0, DT, arrived=T0 + 4.2 * DT)  # nor freeze it
    assert e.dropped["schedule_time"] == 7
    # Mode: a tick message in a self-clocked run, and a schedule in a run of tick messages.
    assert not e.on_tick(5, 5 * DT, (), True, arrived=T0 + 5 * DT)
    m = engine()
    assert m.on_tick(0, 0.0, (), True, arrived=T0)
    assert not m.on_schedule(0, 100, T0, DT, arrived=T0)
    assert e.dropped["tick_mode"] == 1 and m.dropped["tick_mode"] == 1
    assert e.k == 4 and e.take(gather=False, now=T0 + 5 * DT).k == 5  # the schedule held


def test_a_self_clocked_engine_needs_the_time() -> None:
    e = clocked()
    with pytest.raises(ValueError, match="now"):
        e.take(gather=False)


def test_schedule_messages_round_trip_and_are_not_tick_messages() -> None:
    message = bus.ScheduleMessage(4, 99, 1234.5, 0.01, (0, 2))
    payload = bus.encode_schedule(message)
    assert bus.is_schedule(payload) and bus.decode_schedule(payload) == message
    tick = bus.encode_tick(bus.TickMessage(4, 0.04, (), realtime=True))
    assert not bus.is_schedule(tick)
    with pytest.raises(bus.BusMessageError):
        bus.decode_tick(payload)
    with pytest.raises(bus.BusMessageError):
        bus.decode_schedule(tick)
    with pytest.raises(bus.BusMessageError):
        bus.decode_schedule(payload[:-1])


@settings(max_examples=200, deadline=None)
@given(
    wakes=st.lists(st.floats(0.0, 3.0), min_size=1, max_size=80),
    forged=st.lists(
        st.tuples(st.integers(0, 10**6), st.floats(-1e4, 1e4), st.floats(0.0, 0.1)), max_size=8
    ),
)
def test_property_self_clocked_ticks_follow_the_clock_whatever_schedules_are_forged(
    wakes: list[float], forged: list[tuple[int, float, float]]
) -> None:
    """The worker wakes late by any amount (periods in ``wakes``); forged schedules arrive
    between the wakes. Each taken tick is the newest one due on the genuine schedule or
    behind it (never ahead of the clock by more than the slack), ticks only grow, and the
    agent is never frozen: once the genuine schedule is repeated, the next tick due runs."""
    e = clocked(neighbours=())
    now = T0
    for i, late in enumerate(wakes):
        now += late * DT
        for first, offset, when in forged if i % 7 == 3 else ():
            e.on_schedule(first, first + 10**6, T0 + offset, DT, arrived=now + when * DT)
        e.on_schedule(0, 10**6, T0, DT, arrived=now)  # the manager's repeat
        before = e.k
        tick = e.take(gather=False, now=now)
        due = math.floor((now - T0) / DT + 1e-9)
        if tick is not None:
            assert before < tick.k <= due + REALTIME_SLACK_TICKS + 1
        assert e.k <= due + REALTIME_SLACK_TICKS + 1
        nxt = e.next_due()
        assert nxt is not None and nxt - now <= (SCHEDULE_AHEAD_PERIODS + 1) * DT + 1e-9


@pytest.mark.parametrize("rate_hz", [0.5, 1.0, 10.0, 23.0, 50.0, 100.0, 240.0, 1000.0])
def test_the_managers_lead_with_its_pre_roll_is_a_schedule_the_agents_accept(
    rate_hz: float,
) -> None:
    dt = 1.0 / rate_hz
    lead = start_lead(dt, self_clocked=True)
    # 5 periods (at most 50 ms), then the pre-roll: 8 spacings of one period (at most 10 ms)
    assert lead == pytest.approx(min(0.05, 5 * dt) + PREROLL_TICKS * min(dt, 0.01))
    assert start_lead(dt, self_clocked=False) == pytest.approx(min(0.05, 5 * dt))
    e = TickEngine(("a",), NAMES, dt, 8)
    e.running = True
    assert e.on_schedule(0, 100, T0, dt, arrived=T0 - lead), e.counters()
    assert e.next_due() == T0


def test_the_pre_roll_is_spaced_by_the_period_at_most_10_ms_and_ends_before_tick_0() -> None:
    assert preroll_times(1.0, 0.02) == pytest.approx([1.0 - 0.01 * j for j in range(8, 0, -1)])
    assert preroll_times(1.0, 0.004) == pytest.approx([1.0 - 0.004 * j for j in range(8, 0, -1)])
    assert PREROLL_PERIOD_MAX_S == 0.01 and len(preroll_times(0.0, 1.0)) == PREROLL_TICKS
    assert [is_warmup(k) for k in (-8, -1, 0, 1)] == [True, True, False, False]
